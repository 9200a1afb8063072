//! The `grpc` backend's server: unary calls `POST /<Service>/<Method>` over HTTP/2 without
//! TLS (h2c, as `grpcurl -plaintext` and every gRPC client's insecure channel speak it),
//! answered by the module service registered under that name.

use std::collections::HashMap;
use std::convert::Infallible;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::{Arc, RwLock};
use std::task::{Context, Poll};
use std::time::Duration;

use aimrt_net::close::Closing;
use aimrt_net::header::{decode, meta_key};
use aimrt_net::receiving::{self, BodyError, Claim, Receiving, RECEIVING_BYTES};
use aimrt_plugin_api::rpc::{BackendAnswer, CallView};
use aimrt_plugin_api::{meta_keys, RpcStatus, ServiceHost};
use bytes::Bytes;
use http_body::Frame;
use hyper::body::Incoming;
use hyper::header::{self, HeaderMap, HeaderName, HeaderValue};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};

use crate::wire::{self, code};

/// The largest request taken: gRPC's usual limit is 4 MiB; ours is net_plugin's 16 MiB.
pub const MAX_MESSAGE: usize = 16 << 20;

/// How long a request's body may take to arrive when the call has no deadline.
const BODY_TIMEOUT: Duration = Duration::from_secs(60);

/// The context key under which the server hands on the client's address (`ip:port`), as
/// AimRT's servers do.
const REMOTE_ENDPOINT_KEY: &str = "Remote-Endpoint";

/// A body of at most one data frame and one trailers frame: a gRPC request or answer.
#[derive(Debug, Default)]
pub struct GrpcBody {
    data: Option<Bytes>,
    trailers: Option<HeaderMap>,
}

impl GrpcBody {
    /// `data`, then `trailers`.
    pub fn new(data: Option<Bytes>, trailers: Option<HeaderMap>) -> GrpcBody {
        GrpcBody { data, trailers }
    }
}

impl http_body::Body for GrpcBody {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        _: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        if let Some(data) = self.data.take() {
            return Poll::Ready(Some(Ok(Frame::data(data))));
        }
        Poll::Ready(self.trailers.take().map(|t| Ok(Frame::trailers(t))))
    }

    fn is_end_stream(&self) -> bool {
        self.data.is_none() && self.trailers.is_none()
    }
}

/// The paths this server serves (`/Service/Method`), each with its full function name
/// (shared: a call takes a reference, not a copy).
pub(crate) type Routes = Arc<RwLock<HashMap<String, Arc<str>>>>;

/// What every connection needs.
#[derive(Clone)]
pub(crate) struct Server {
    pub(crate) host: ServiceHost,
    pub(crate) routes: Routes,
    /// The bytes of requests arriving on all connections, and the calls refused for them.
    pub(crate) receiving: Arc<Receiving>,
    /// The connections' permits and the signal to close: the listener stops and every
    /// connection closes gracefully (HTTP/2 `GOAWAY`, then the calls it took are answered).
    pub(crate) closing: Closing,
}

impl Server {
    /// A server that nothing closes (tests, fuzzing).
    pub(crate) fn detached(host: ServiceHost, routes: Routes) -> Server {
        Server {
            host,
            routes,
            receiving: Receiving::new(RECEIVING_BYTES, "grpc_plugin"),
            closing: Closing::never(MAX_CONNECTIONS),
        }
    }
}

/// Connections served at once at most (as net_plugin's HTTP server by default); more wait
/// in the kernel's accept queue until one closes.
pub const MAX_CONNECTIONS: usize = 4096;

/// Accepts connections until the backend closes or the runtime stops.
pub(crate) async fn accept(listener: aimrt_net::close::Listener, server: Server) {
    let closing = server.closing.clone();
    let what = ("grpc_plugin", "raise the open-file limit (ulimit -n)");
    aimrt_net::close::accept(listener, closing, what, move |stream, remote| {
        serve_connection(stream, remote, server.clone())
    })
    .await;
}

/// How long a connection may bring nothing before the server pings the client, and how
/// long it then waits for the answer before closing the connection: a client that
/// vanished without closing it (a cut cable, a machine that lost power) would otherwise
/// keep its connection, one of [`MAX_CONNECTIONS`], for good. Any HTTP/2 client answers
/// pings; gRPC's own clients do not limit the pings they receive.
pub const KEEP_ALIVE: (Duration, Duration) = (Duration::from_secs(60), Duration::from_secs(20));

/// Serves the calls of one connection until it closes. A client that does not speak
/// HTTP/2 is dropped (counted in the log at debug level).
pub(crate) async fn serve_connection<S>(stream: S, remote: SocketAddr, server: Server)
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
{
    serve(stream, remote, server, KEEP_ALIVE).await;
}

/// [`serve_connection`] with the keep-alive `(interval, timeout)`.
async fn serve<S>(stream: S, remote: SocketAddr, server: Server, keep_alive: (Duration, Duration))
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
{
    let remote: Arc<str> = remote.to_string().into();
    let closing = server.closing.clone();
    let service = hyper::service::service_fn(move |req| {
        let (server, remote) = (server.clone(), remote.clone());
        async move { Ok::<_, Infallible>(route(req, &remote, &server).await) }
    });
    let connection = hyper::server::conn::http2::Builder::new(TokioExecutor::new())
        .timer(TokioTimer::new())
        .keep_alive_interval(keep_alive.0)
        .keep_alive_timeout(keep_alive.1)
        .serve_connection(TokioIo::new(stream), service);
    tokio::pin!(connection);
    let served = tokio::select! {
        served = connection.as_mut() => served,
        () = closing.closed() => {
            // `GOAWAY`: the client learns which calls were taken (they are answered)
            // and that the others never ran.
            connection.as_mut().graceful_shutdown();
            connection.await
        }
    };
    if let Err(e) = served {
        tracing::debug!(target: "aimrt", "grpc_plugin: connection ended: {e}");
    }
}

/// An answer that is not gRPC: `status` with `text`, for requests gRPC's rules answer
/// with HTTP statuses (not POST, not a gRPC content type).
fn http_error(status: StatusCode, text: &str) -> Response<GrpcBody> {
    let mut r = Response::new(GrpcBody::new(Some(Bytes::from(text.to_owned())), None));
    *r.status_mut() = status;
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; charset=utf-8"),
    );
    r
}

/// A failed call as gRPC's "trailers only" answer: status 200, `grpc-status`,
/// `grpc-message` and AimRT's code in the headers, no body.
pub(crate) fn failure(
    grpc: u32,
    aimrt: Option<RpcStatus>,
    message: &str,
    content_type: &'static str,
) -> Response<GrpcBody> {
    let mut r = Response::new(GrpcBody::default());
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    put_status(h, grpc, aimrt, message);
    r
}

/// Sets `grpc-status`, `grpc-message` (when there is one) and AimRT's code.
fn put_status(h: &mut HeaderMap, grpc: u32, aimrt: Option<RpcStatus>, message: &str) {
    h.insert(
        HeaderName::from_static("grpc-status"),
        HeaderValue::from(grpc),
    );
    if !message.is_empty() {
        if let Ok(v) = HeaderValue::from_str(&wire::encode_message(message)) {
            h.insert(HeaderName::from_static("grpc-message"), v);
        }
    }
    if let Some(s) = aimrt {
        h.insert(
            HeaderName::from_static(wire::AIMRT_STATUS),
            HeaderValue::from(s.code()),
        );
    }
}

/// A request header read per call, by a name made once (a `&str` is parsed at each
/// lookup; `grpc-timeout` is [`wire::GRPC_TIMEOUT`]).
static GRPC_ENCODING: HeaderName = HeaderName::from_static("grpc-encoding");

/// Headers that are HTTP/2's or gRPC's own, never a call's meta.
fn is_protocol_header(name: &HeaderName) -> bool {
    name == header::CONTENT_TYPE
        || name == header::CONTENT_LENGTH
        || name == header::TE
        || name == header::USER_AGENT
        || name == header::HOST
        || name == header::ACCEPT_ENCODING
        || name.as_str().starts_with("grpc-")
        || name.as_str() == "remote-endpoint"
}

/// Answers one call from `remote`.
async fn route(req: Request<Incoming>, remote: &str, server: &Server) -> Response<GrpcBody> {
    if req.method() != Method::POST {
        return http_error(
            StatusCode::METHOD_NOT_ALLOWED,
            &format!("{} is not a gRPC call; gRPC calls are POST", req.method()),
        );
    }
    let content_type = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let Some(format) = wire::serialization_of(content_type) else {
        return http_error(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            &format!(
                "content-type '{content_type}' is not gRPC; send application/grpc (pb) or application/grpc+json"
            ),
        );
    };
    let answer_type = wire::content_type_of(format).unwrap_or("application/grpc");
    let path = req.uri().path().to_owned();
    let func = server
        .routes
        .read()
        .unwrap_or_else(|e| e.into_inner())
        .get(&path)
        .cloned();
    let Some(func) = func else {
        return failure(
            code::UNIMPLEMENTED,
            Some(RpcStatus::SVR_NOT_FOUND),
            &format!("no service function at '{path}' here: aimrt.rpc.servers_options does not give it to the grpc backend, or no module serves it"),
            answer_type,
        );
    };
    let (parts, body) = req.into_parts();
    if parts
        .headers
        .get(&GRPC_ENCODING)
        .is_some_and(|v| v.as_bytes() != b"identity")
    {
        return failure(
            code::UNIMPLEMENTED,
            Some(RpcStatus::SVR_INVALID_DESERIALIZATION_TYPE),
            "compressed messages (grpc-encoding) are not supported; send them uncompressed",
            answer_type,
        );
    }
    let timeout = parts
        .headers
        .get(&wire::GRPC_TIMEOUT)
        .and_then(|v| v.to_str().ok())
        .and_then(wire::parse_timeout);
    let mut claim = Claim::new(&server.receiving);
    let collected = tokio::time::timeout(
        timeout.unwrap_or(BODY_TIMEOUT),
        receiving::collect(body, MAX_MESSAGE + wire::PREFIX, &mut claim),
    )
    .await;
    let bytes = match collected {
        Ok(Ok(b)) => b,
        Ok(Err(BodyError::TooLarge(_))) => {
            return failure(
                code::RESOURCE_EXHAUSTED,
                Some(RpcStatus::SVR_DESERIALIZATION_FAILED),
                &format!("the message is larger than the limit of {MAX_MESSAGE} bytes"),
                answer_type,
            )
        }
        Ok(Err(BodyError::Full(full))) => {
            server.receiving.refuse(format_args!(
                "a call was refused (RESOURCE_EXHAUSTED): {full}"
            ));
            return failure(
                code::RESOURCE_EXHAUSTED,
                Some(RpcStatus::SVR_NOT_READY),
                &format!("{full}; try again"),
                answer_type,
            );
        }
        Ok(Err(e)) => {
            return failure(
                code::INTERNAL,
                Some(RpcStatus::SVR_BACKEND_INTERNAL_ERROR),
                &format!("cannot read the request: {e}"),
                answer_type,
            )
        }
        Err(_) => {
            return failure(
                code::DEADLINE_EXCEEDED,
                Some(RpcStatus::TIMEOUT),
                "the request did not arrive within its deadline",
                answer_type,
            )
        }
    };
    let message = match wire::unframe(&bytes) {
        Ok(m) => m,
        Err(e) => {
            let grpc = match e {
                wire::FrameError::Compressed => code::UNIMPLEMENTED,
                _ => code::INVALID_ARGUMENT,
            };
            return failure(
                grpc,
                Some(RpcStatus::SVR_DESERIALIZATION_FAILED),
                &e.to_string(),
                answer_type,
            );
        }
    };
    // The context: every header that is not the protocol's, decoded as AimRT's net_plugin
    // encodes meta; the caller's address; the serialization type.
    let mut meta: Vec<(std::borrow::Cow<'_, str>, std::borrow::Cow<'_, str>)> =
        Vec::with_capacity(parts.headers.len() + 2);
    for (name, value) in &parts.headers {
        if is_protocol_header(name) {
            continue;
        }
        let key = meta_key(name.as_str());
        if key == meta_keys::SERIALIZATION_TYPE || meta.iter().any(|(k, _)| *k == key) {
            continue;
        }
        meta.push((key, decode(value.as_bytes())));
    }
    meta.push((REMOTE_ENDPOINT_KEY.into(), remote.into()));
    meta.push((meta_keys::SERIALIZATION_TYPE.into(), format.into()));
    let (tx, rx) = tokio::sync::oneshot::channel();
    {
        let pairs =
            aimrt_plugin_api::ffi::meta_of(meta.iter().map(|(k, v)| (k.as_ref(), v.as_ref())));
        server.host.call_view(
            CallView::new(&func, &pairs, timeout, message),
            move |answer| {
                let _ = tx.send(answer);
            },
        );
    }
    match rx.await {
        Ok(answer) => answer_response(answer, answer_type),
        Err(_) => failure(
            code::INTERNAL,
            Some(RpcStatus::SVR_BACKEND_INTERNAL_ERROR),
            "the service dropped the call without an answer",
            answer_type,
        ),
    }
}

/// A service's answer as gRPC: the message and `grpc-status: 0` in the trailers, or a
/// trailers-only failure with the status.
fn answer_response(answer: BackendAnswer, content_type: &'static str) -> Response<GrpcBody> {
    if !answer.status.is_ok() {
        let message = if answer.detail.is_empty() {
            format!("{} ({})", answer.status.text(), answer.status.code())
        } else {
            answer.detail
        };
        return failure(
            wire::grpc_code_of(answer.status),
            Some(answer.status),
            &message,
            content_type,
        );
    }
    let mut trailers = HeaderMap::new();
    put_status(&mut trailers, code::OK, None, "");
    let mut r = Response::new(GrpcBody::new(
        Some(Bytes::from(wire::frame(&answer.body))),
        Some(trailers),
    ));
    r.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    r
}

/// The HEADERS frame (stream 1, HPACK without Huffman or indexing) of a gRPC call of
/// `/a.B/C` in `pb`, as a client opens it.
fn call_headers() -> Vec<u8> {
    let mut block = vec![0x83, 0x86]; // :method POST, :scheme http (static table)
    block.extend_from_slice(&[0x04, 6]); // :path, literal value
    block.extend_from_slice(b"/a.B/C");
    block.extend_from_slice(&[0x01, 1, b'x']); // :authority x
    block.extend_from_slice(&[0x0f, 0x10, 16]); // content-type (index 31)
    block.extend_from_slice(b"application/grpc");
    block.extend_from_slice(&[0x00, 2]);
    block.extend_from_slice(b"te");
    block.push(8);
    block.extend_from_slice(b"trailers");
    let len = u32::try_from(block.len()).unwrap_or(0).to_be_bytes();
    // Type HEADERS, flags END_HEADERS, stream 1.
    let mut frame = vec![len[1], len[2], len[3], 1, 0x4, 0, 0, 0, 1];
    frame.extend_from_slice(&block);
    frame
}

/// Feeds `input`, after HTTP/2's client preface and an empty SETTINGS frame, as one
/// connection's bytes to the server (with a service `/a.B/C` that echoes the request and
/// fails on `fail`) and returns what it answered. An input that starts with byte 1 has
/// the rest follow the HEADERS frame of a gRPC call of `/a.B/C` on stream 1, so its bytes
/// are that call's DATA frames (and whatever else). For fuzzing: whatever the frames, this
/// must return, not panic or hang.
pub fn serve_bytes(input: &[u8]) -> Vec<u8> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let host = aimrt_net::__fuzz::echo_host();
    let Ok(runtime) = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    else {
        return Vec::new();
    };
    runtime.block_on(async move {
        let (mut client, server) = tokio::io::duplex(1 << 20);
        let routes = Routes::default();
        routes
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert("/a.B/C".into(), "pb:/a.B/C".into());
        let served = tokio::spawn(serve_connection(
            server,
            SocketAddr::from(([127, 0, 0, 1], 1)),
            Server::detached(host, routes),
        ));
        let mut bytes = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
        bytes.extend_from_slice(&[0, 0, 0, 4, 0, 0, 0, 0, 0]);
        match input.split_first() {
            Some((1, rest)) => {
                bytes.extend_from_slice(&call_headers());
                bytes.extend_from_slice(rest);
            }
            _ => bytes.extend_from_slice(input),
        }
        let _ = client.write_all(&bytes).await;
        // Everything runs on this thread: a few turns let the server read the frames and
        // answer the calls they complete (the echo answers at once) before the end of the
        // stream closes the connection; a call left open is cut off there.
        for _ in 0..64 {
            tokio::task::yield_now().await;
        }
        let _ = client.shutdown().await;
        let mut out = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(2), client.read_to_end(&mut out)).await;
        served.abort();
        out
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn test_server() -> Server {
        Server::detached(aimrt_net::__fuzz::echo_host(), Routes::default())
    }

    fn runtime() -> tokio::runtime::Runtime {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap()
    }

    const PING: (Duration, Duration) = (Duration::from_millis(50), Duration::from_millis(50));

    /// hyper's HTTP/2 client over `io`, its connection served by a task.
    async fn h2_client(
        io: tokio::io::DuplexStream,
    ) -> (
        hyper::client::conn::http2::SendRequest<GrpcBody>,
        tokio::task::JoinHandle<hyper::Result<()>>,
    ) {
        let (sender, connection) = hyper::client::conn::http2::Builder::new(TokioExecutor::new())
            .timer(TokioTimer::new())
            .handshake::<_, GrpcBody>(TokioIo::new(io))
            .await
            .unwrap();
        (sender, tokio::spawn(connection))
    }

    #[test]
    fn a_client_that_goes_silent_has_its_connection_closed() {
        use tokio::io::AsyncWriteExt;
        runtime().block_on(async {
            let (mut client, server) = tokio::io::duplex(1 << 20);
            let served = tokio::spawn(serve(
                server,
                SocketAddr::from(([127, 0, 0, 1], 1)),
                test_server(),
                PING,
            ));
            // The preface and SETTINGS, then nothing more: no answer to the server's
            // SETTINGS or its pings, and the connection left open, as by a vanished peer.
            let mut hello = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
            hello.extend_from_slice(&[0, 0, 0, 4, 0, 0, 0, 0, 0]);
            client.write_all(&hello).await.unwrap();
            let ended = tokio::time::timeout(Duration::from_secs(5), served).await;
            assert!(ended.is_ok(), "the connection is still served");
            drop(client);
        });
    }

    #[test]
    fn a_quiet_client_that_answers_pings_keeps_its_connection() {
        runtime().block_on(async {
            let (client, server) = tokio::io::duplex(1 << 20);
            let served = tokio::spawn(serve(
                server,
                SocketAddr::from(([127, 0, 0, 1], 1)),
                test_server(),
                PING,
            ));
            let (sender, conn) = h2_client(client).await;
            // Ten intervals without a call: hyper's client answers the pings.
            tokio::time::sleep(PING.0 * 10).await;
            assert!(!served.is_finished() && !sender.is_closed());
            drop(sender);
            let _ = conn.await;
        });
    }

    #[test]
    fn closing_answers_the_calls_taken_then_ends_the_connection() {
        runtime().block_on(async {
            let closer = aimrt_net::close::Closer::new(MAX_CONNECTIONS);
            let mut server = test_server();
            server.closing = closer.closing();
            let (client, io) = tokio::io::duplex(1 << 20);
            let served = tokio::spawn(serve(
                io,
                SocketAddr::from(([127, 0, 0, 1], 1)),
                server,
                KEEP_ALIVE,
            ));
            let (mut sender, conn) = h2_client(client).await;
            let call = || {
                let mut req =
                    Request::new(GrpcBody::new(Some(Bytes::from(wire::frame(b""))), None));
                *req.method_mut() = Method::POST;
                *req.uri_mut() = "http://127.0.0.1/a.B/C".parse().unwrap();
                req.headers_mut().insert(
                    header::CONTENT_TYPE,
                    HeaderValue::from_static("application/grpc"),
                );
                req
            };
            let answered = sender.send_request(call()).await.unwrap();
            assert_eq!(answered.status(), StatusCode::OK);
            // Told to close (the wait for the connections to end is left to the test).
            closer.close(Duration::ZERO);
            // GOAWAY, then the connection ends: nothing was left to answer.
            let ended = tokio::time::timeout(Duration::from_secs(5), served).await;
            assert!(ended.is_ok(), "the connection is still served");
            let _ = tokio::time::timeout(Duration::from_secs(5), conn).await;
            assert!(sender.is_closed());
        });
    }

    #[test]
    fn frames_of_garbage_get_the_connection_closed_never_a_panic() {
        for input in [
            &b""[..],
            &[0xff; 64],
            // A HEADERS frame on stream 1 whose block is not HPACK.
            &[0, 0, 3, 1, 5, 0, 0, 0, 1, 0xff, 0xff, 0xff],
            // A DATA frame on a stream never opened.
            &[0, 0, 2, 0, 1, 0, 0, 0, 3, b'h', b'i'],
        ] {
            let out = serve_bytes(input);
            // The server's SETTINGS frame comes first, whatever followed the preface.
            assert!(out.len() >= 9 && out[3] == 4, "{input:?}: {out:?}");
        }
    }

    /// The frame types of `out`, in order.
    fn frame_types(out: &[u8]) -> Vec<u8> {
        let mut types = Vec::new();
        let mut i = 0;
        while i + 9 <= out.len() {
            let len =
                usize::from(out[i]) << 16 | usize::from(out[i + 1]) << 8 | usize::from(out[i + 2]);
            types.push(out[i + 3]);
            i += 9 + len;
        }
        types
    }

    #[test]
    fn a_call_in_raw_frames_is_answered_and_a_cut_one_too() {
        let data = |payload: &[u8]| {
            let mut f = vec![0, 0, payload.len() as u8, 0, 0x1, 0, 0, 0, 1];
            f.extend_from_slice(payload);
            f
        };
        // A whole call: HEADERS (status 200), DATA (the echoed message), HEADERS
        // (trailers, grpc-status 0).
        let mut input = vec![1];
        input.extend_from_slice(&data(&[0, 0, 0, 0, 2, b'h', b'i']));
        let out = serve_bytes(&input);
        let types = frame_types(&out);
        assert!(types.windows(3).any(|w| w == [1, 0, 1]), "{types:?}");
        assert!(
            out.windows(7).any(|w| w == [0, 0, 0, 0, 2, b'h', b'i']),
            "the echo"
        );
        // A message cut short: one HEADERS frame, trailers only, no DATA.
        let out = serve_bytes(&[&[1][..], &data(&[0, 0, 0, 0, 9, b'h'])].concat());
        let types = frame_types(&out);
        assert!(types.contains(&1) && !types.contains(&0), "{types:?}");
    }

    /// Requests arriving on all connections hold at most the server's budget: with one
    /// call in the middle of a 2 MiB message, another 2 MiB call is refused
    /// (`RESOURCE_EXHAUSTED`, AimRT's 1009) part way and counted; a small call is
    /// answered meanwhile, and the first is once its message is whole.
    #[test]
    fn requests_arriving_on_all_connections_hold_at_most_the_servers_budget() {
        use http_body_util::{BodyExt, Channel};
        runtime().block_on(async {
            let mut server = test_server();
            server.receiving = Receiving::new(3 << 20, "grpc_plugin");
            server
                .routes
                .write()
                .unwrap()
                .insert("/a.B/C".into(), "pb:/a.B/C".into());
            let budget = server.receiving.clone();
            let (client, io) = tokio::io::duplex(4 << 20);
            tokio::spawn(serve(
                io,
                SocketAddr::from(([127, 0, 0, 1], 1)),
                server,
                KEEP_ALIVE,
            ));
            let (mut sender, connection) =
                hyper::client::conn::http2::Builder::new(TokioExecutor::new())
                    .timer(TokioTimer::new())
                    .handshake::<_, Channel<Bytes, Infallible>>(TokioIo::new(client))
                    .await
                    .unwrap();
            tokio::spawn(connection);
            let call = |body: Channel<Bytes, Infallible>| {
                let mut req = Request::new(body);
                *req.method_mut() = Method::POST;
                *req.uri_mut() = "http://127.0.0.1/a.B/C".parse().unwrap();
                req.headers_mut().insert(
                    header::CONTENT_TYPE,
                    HeaderValue::from_static("application/grpc"),
                );
                req
            };
            let message = Bytes::from(wire::frame(&vec![b'x'; 2 << 20]));
            // Three quarters of a 2 MiB message, then nothing yet.
            let (mut first_body, body) = Channel::new(4);
            let first = tokio::spawn(sender.send_request(call(body)));
            first_body
                .send_data(message.slice(..3 << 19))
                .await
                .unwrap();
            let by = std::time::Instant::now() + Duration::from_secs(10);
            while budget.held() < (3 << 19) - aimrt_net::receiving::UNCOUNTED {
                assert!(std::time::Instant::now() < by, "the first message was held");
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
            // A whole second one would pass 3 MiB.
            let (mut second_body, body) = Channel::new(4);
            let second = tokio::spawn(sender.send_request(call(body)));
            for part in message.chunks(256 << 10) {
                if second_body
                    .send_data(message.slice_ref(part))
                    .await
                    .is_err()
                {
                    break;
                }
            }
            drop(second_body);
            let answer = second.await.unwrap().unwrap();
            let status = |name: &str| {
                answer
                    .headers()
                    .get(name)
                    .map(|v| v.to_str().unwrap().to_owned())
            };
            assert_eq!(
                status("grpc-status").as_deref(),
                Some("8"),
                "RESOURCE_EXHAUSTED"
            );
            assert_eq!(status(wire::AIMRT_STATUS).as_deref(), Some("1009"));
            let said = status("grpc-message").unwrap_or_default();
            assert!(said.contains("bytes of messages are arriving"), "{said}");
            assert_eq!(budget.refused(), 1);
            // A small call is answered however full the budget is.
            let (mut small_body, body) = Channel::new(1);
            small_body
                .send_data(Bytes::from(wire::frame(b"hi")))
                .await
                .unwrap();
            drop(small_body);
            let small = sender.send_request(call(body)).await.unwrap();
            assert_eq!(
                small.headers().get("grpc-status"),
                None,
                "status in the trailers: 0"
            );
            assert_eq!(small.status(), StatusCode::OK);
            // The first message completes and is answered; the budget is given back.
            first_body
                .send_data(message.slice(3 << 19..))
                .await
                .unwrap();
            drop(first_body);
            let answer = first.await.unwrap().unwrap();
            assert_eq!(answer.status(), StatusCode::OK);
            assert_eq!(answer.headers().get("grpc-status"), None);
            let echoed = answer.into_body().collect().await.unwrap().to_bytes();
            assert_eq!(echoed.len(), message.len());
            assert_eq!(budget.held(), 0);
        });
    }
}
