//! Sends finished spans to the collector: a thread takes them from a bounded queue and
//! posts them in batches (every second, or at 512 spans) as one OTLP/HTTP protobuf
//! request each. A full queue drops the span and counts it; a request the collector
//! refuses or that fails counts its spans. At shutdown what is queued is sent (waiting at
//! most 5 s), then one line says what happened to every span.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use crate::lock;
use aimrt_plugin_api::RateLimit;
use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use prost::Message;

use crate::otlp::{
    ExportTraceServiceRequest, InstrumentationScope, KeyValue, Resource, ResourceSpans, ScopeSpans,
    Span,
};

/// Spans waiting to be sent at most; more are dropped and counted.
pub const QUEUE: usize = 4096;
/// Spans in one request at most.
pub const BATCH: usize = 512;
/// How long spans wait to be sent at most.
pub const INTERVAL: Duration = Duration::from_secs(1);
/// How long one request may take.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);

/// Where spans go: `http://host:port/path`, or `https://` for TLS.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Endpoint {
    /// `host:port`.
    pub authority: String,
    /// The host, without the brackets of an IPv6 address: the name TLS checks.
    pub host: String,
    /// `/v1/traces`, …
    pub path: String,
    /// Whether requests go over TLS (`https://`).
    pub tls: bool,
}

impl Endpoint {
    /// Reads `http://host[:port][/path]` or `https://…` (port 80 or 443, path `/` when
    /// left out); `Err` says what is wrong.
    ///
    /// ```
    /// use aimrt_opentelemetry::exporter::Endpoint;
    /// let e = Endpoint::parse("http://localhost:4318/v1/traces").unwrap();
    /// assert_eq!((e.authority.as_str(), e.path.as_str()), ("localhost:4318", "/v1/traces"));
    /// let e = Endpoint::parse("https://collector.example/v1/traces").unwrap();
    /// assert_eq!((e.authority.as_str(), e.tls), ("collector.example:443", true));
    /// assert!(Endpoint::parse("grpc://collector:4317").unwrap_err().contains("not an http"));
    /// ```
    pub fn parse(url: &str) -> Result<Endpoint, String> {
        let (rest, tls) = match (url.strip_prefix("http://"), url.strip_prefix("https://")) {
            (Some(rest), _) => (rest, false),
            (_, Some(rest)) => (rest, true),
            _ => {
                return Err(format!(
                    "'{url}' is not an http:// or https:// URL; write http://host:4318/v1/traces"
                ))
            }
        };
        let (authority, path) = match rest.find('/') {
            Some(at) => (&rest[..at], &rest[at..]),
            None => (rest, "/"),
        };
        let (host, port) = match authority.find(']') {
            // `[v6]` or `[v6]:port`.
            Some(end) if authority.starts_with('[') => {
                let (host, rest) = authority.split_at(end + 1);
                (host, rest.strip_prefix(':'))
            }
            _ => match authority.rsplit_once(':') {
                Some((h, p)) => (h, Some(p)),
                None => (authority, None),
            },
        };
        if host.is_empty() {
            return Err(format!("'{url}' names no host"));
        }
        let port =
            match port {
                None if tls => 443,
                None => 80,
                Some(p) => p.parse::<u16>().ok().filter(|p| *p != 0).ok_or_else(|| {
                    format!("'{url}': port '{p}' is not a number from 1 to 65535")
                })?,
            };
        let bare = host.trim_start_matches('[').trim_end_matches(']');
        if tls && rustls::pki_types::ServerName::try_from(bare).is_err() {
            return Err(format!(
                "'{url}': '{bare}' is not a host name or address TLS can check"
            ));
        }
        Ok(Endpoint {
            authority: format!("{host}:{port}"),
            host: bare.to_owned(),
            path: path.to_owned(),
            tls,
        })
    }
}

/// What happened to the spans.
#[derive(Debug, Default)]
pub(crate) struct Stats {
    pub(crate) recorded: AtomicU64,
    pub(crate) exported: AtomicU64,
    /// Dropped at a full queue.
    pub(crate) dropped: AtomicU64,
    /// In requests that failed or were refused.
    pub(crate) failed: AtomicU64,
}

/// The exporter.
pub(crate) struct Exporter {
    queue: Mutex<Option<SyncSender<Span>>>,
    ended: Mutex<Option<mpsc::Receiver<()>>>,
    pub(crate) stats: Arc<Stats>,
    alarm: RateLimit,
}

impl Exporter {
    /// Starts the thread that sends to `endpoint` what [`record`](Self::record) queues,
    /// as the resource `resource` (service.name and the configured attributes) and the
    /// scope `scope`.
    pub(crate) fn start(
        endpoint: Endpoint,
        resource: Vec<KeyValue>,
        scope: String,
    ) -> Result<Exporter, String> {
        let (tx, rx) = mpsc::sync_channel::<Span>(QUEUE);
        let (done_tx, done_rx) = mpsc::channel();
        let stats = Arc::new(Stats::default());
        let sending = Sender {
            endpoint,
            resource,
            scope,
            stats: stats.clone(),
            alarm: RateLimit::from_millis(10_000),
        };
        std::thread::Builder::new()
            .name("aimrt_otlp".into())
            .spawn(move || {
                sending.run(&rx);
                let _ = done_tx.send(());
            })
            .map_err(|e| format!("cannot start the exporter's thread: {e}"))?;
        Ok(Exporter {
            queue: Mutex::new(Some(tx)),
            ended: Mutex::new(Some(done_rx)),
            stats,
            alarm: RateLimit::from_millis(1000),
        })
    }

    /// Queues a finished span; a full queue drops it (counted, said at most once a second).
    pub(crate) fn record(&self, span: Span) {
        self.stats.recorded.fetch_add(1, Ordering::Relaxed);
        let queue = lock(&self.queue).clone();
        let refused = match queue {
            Some(q) => match q.try_send(span) {
                Ok(()) => return,
                Err(TrySendError::Full(_)) => "the exporter's queue is full",
                Err(TrySendError::Disconnected(_)) => "the exporter has stopped",
            },
            None => "the plugin has shut down",
        };
        self.stats.dropped.fetch_add(1, Ordering::Relaxed);
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(target: "aimrt", "opentelemetry_plugin: a span is dropped: {refused} ({QUEUE} spans wait for the collector) ({held} more such lines held back since the last)");
        }
    }

    /// Sends what is queued (waiting at most 5 s), stops the thread and says what
    /// happened to every span.
    pub(crate) fn close(&self) {
        drop(lock(&self.queue).take());
        if let Some(ended) = lock(&self.ended).take() {
            if ended.recv_timeout(REQUEST_TIMEOUT).is_err() {
                tracing::warn!(target: "aimrt", "opentelemetry_plugin: the exporter did not finish within 5 s; its spans left are not sent");
            }
        }
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let s = &self.stats;
        tracing::info!(target: "aimrt", "opentelemetry_plugin: {} spans recorded, {} exported, {} dropped at a full queue, {} in requests that failed",
            g(&s.recorded), g(&s.exported), g(&s.dropped), g(&s.failed));
    }
}

/// The exporter's thread.
struct Sender {
    endpoint: Endpoint,
    resource: Vec<KeyValue>,
    scope: String,
    stats: Arc<Stats>,
    alarm: RateLimit,
}

impl Sender {
    fn run(&self, rx: &mpsc::Receiver<Span>) {
        let Some(rt) = runtime() else {
            tracing::error!(target: "aimrt", "opentelemetry_plugin: cannot start the exporter's runtime: no span is sent");
            return;
        };
        let mut batch = Vec::new();
        let mut due = Instant::now() + INTERVAL;
        loop {
            let wait = due.saturating_duration_since(Instant::now());
            let open = match rx.recv_timeout(wait) {
                Ok(span) => {
                    batch.push(span);
                    true
                }
                Err(RecvTimeoutError::Timeout) => true,
                Err(RecvTimeoutError::Disconnected) => false,
            };
            if !open || batch.len() >= BATCH || Instant::now() >= due {
                if !batch.is_empty() {
                    self.send(&rt, std::mem::take(&mut batch));
                }
                due = Instant::now() + INTERVAL;
            }
            if !open {
                return;
            }
        }
    }

    fn send(&self, rt: &tokio::runtime::Runtime, spans: Vec<Span>) {
        let n = spans.len() as u64;
        let request = ExportTraceServiceRequest {
            resource_spans: vec![ResourceSpans {
                resource: Some(Resource {
                    attributes: self.resource.clone(),
                }),
                scope_spans: vec![ScopeSpans {
                    scope: Some(InstrumentationScope {
                        name: self.scope.clone(),
                        version: String::new(),
                    }),
                    spans,
                }],
            }],
        };
        match post_blocking(rt, &self.endpoint, request.encode_to_vec(), REQUEST_TIMEOUT) {
            Ok(()) => {
                self.stats.exported.fetch_add(n, Ordering::Relaxed);
            }
            Err(why) => {
                self.stats.failed.fetch_add(n, Ordering::Relaxed);
                if let Some(held) = self.alarm.admit() {
                    tracing::warn!(target: "aimrt", "opentelemetry_plugin: {n} spans not exported to {}: {why} ({held} more failed requests since the last such line)", self.endpoint);
                }
            }
        }
    }
}

impl std::fmt::Display for Endpoint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let scheme = if self.tls { "https" } else { "http" };
        write!(f, "{scheme}://{}{}", self.authority, self.path)
    }
}

/// A current-thread runtime for an exporter's thread.
pub(crate) fn runtime() -> Option<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .ok()
}

/// One `POST` of an OTLP protobuf `body` to `endpoint`, given `timeout`; `Err` says why
/// it failed.
pub(crate) fn post_blocking(
    rt: &tokio::runtime::Runtime,
    endpoint: &Endpoint,
    body: Vec<u8>,
    timeout: Duration,
) -> Result<(), String> {
    rt.block_on(async { tokio::time::timeout(timeout, post(endpoint, body)).await })
        .unwrap_or_else(|_| Err(format!("no answer within {} ms", timeout.as_millis())))
}

/// The TLS set-up of `https://` collectors: the system's CA certificates (or those of the
/// PEM file `SSL_CERT_FILE`, or of the folder `SSL_CERT_DIR`), read once; `Err` when
/// there are none.
pub(crate) fn tls() -> Result<tokio_rustls::TlsConnector, String> {
    static TLS: OnceLock<Result<tokio_rustls::TlsConnector, String>> = OnceLock::new();
    TLS.get_or_init(|| {
        let found = rustls_native_certs::load_native_certs();
        let mut roots = rustls::RootCertStore::empty();
        let (added, _) = roots.add_parsable_certificates(found.certs);
        if added == 0 {
            let why: Vec<String> = found.errors.iter().map(ToString::to_string).collect();
            return Err(format!(
                "https: no CA certificate found on this system{}: install its CA certificates (the ca-certificates package) or set SSL_CERT_FILE to a PEM file of the CAs to trust",
                if why.is_empty() { String::new() } else { format!(" ({})", why.join("; ")) }
            ));
        }
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let config = rustls::ClientConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .map_err(|e| format!("https: cannot set up TLS: {e}"))?
            .with_root_certificates(roots)
            .with_no_client_auth();
        Ok(tokio_rustls::TlsConnector::from(Arc::new(config)))
    })
    .clone()
}

async fn post(e: &Endpoint, body: Vec<u8>) -> Result<(), String> {
    let stream = tokio::net::TcpStream::connect(&e.authority)
        .await
        .map_err(|err| format!("cannot connect: {err}"))?;
    let _ = stream.set_nodelay(true);
    if !e.tls {
        return exchange(stream, e, body).await;
    }
    let name = rustls::pki_types::ServerName::try_from(e.host.clone())
        .map_err(|_| format!("'{}' is not a host name TLS can check", e.host))?;
    let stream = tls()?
        .connect(name, stream)
        .await
        .map_err(|err| format!("TLS handshake failed: {err}"))?;
    exchange(stream, e, body).await
}

/// The request and its answer on a connected `io`.
async fn exchange<S>(io: S, e: &Endpoint, body: Vec<u8>) -> Result<(), String>
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
{
    let (mut sender, connection) =
        hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(io))
            .await
            .map_err(|err| format!("HTTP handshake failed: {err}"))?;
    tokio::spawn(connection);
    let request = hyper::Request::post(&e.path)
        .header(hyper::header::HOST, &e.authority)
        .header(hyper::header::CONTENT_TYPE, "application/x-protobuf")
        .body(Full::new(Bytes::from(body)))
        .map_err(|err| format!("bad request: {err}"))?;
    let answer = sender
        .send_request(request)
        .await
        .map_err(|err| format!("request failed: {err}"))?;
    let status = answer.status();
    let text = answer
        .into_body()
        .collect()
        .await
        .map(|b| {
            String::from_utf8_lossy(&b.to_bytes())
                .chars()
                .take(200)
                .collect::<String>()
        })
        .unwrap_or_default();
    if status.is_success() {
        Ok(())
    } else {
        Err(format!("the collector answered {status}: {text}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn collector_urls_are_read_or_refused_with_why() {
        for (url, expected) in [
            ("http://h:4318/v1/traces", Ok(("h:4318", "/v1/traces"))),
            ("http://h", Ok(("h:80", "/"))),
            (
                "http://[::1]:4318/v1/traces",
                Ok(("[::1]:4318", "/v1/traces")),
            ),
            ("http://[::1]/v1/traces", Ok(("[::1]:80", "/v1/traces"))),
            ("http://:4318/v1/traces", Err("names no host")),
            ("http://h:0/", Err("port '0'")),
            ("http://h:x/", Err("port 'x'")),
            ("ftp://h/", Err("not an http:// or https:// URL")),
            ("https://h/v1/metrics", Ok(("h:443", "/v1/metrics"))),
            ("https://[::1]:4318/", Ok(("[::1]:4318", "/"))),
            ("https://bad_host!/", Err("'bad_host!' is not a host name")),
        ] {
            match (Endpoint::parse(url), expected) {
                (Ok(e), Ok((authority, path))) => {
                    assert_eq!(
                        (e.authority.as_str(), e.path.as_str()),
                        (authority, path),
                        "{url}"
                    );
                    assert_eq!(e.tls, url.starts_with("https://"), "{url}");
                }
                (Err(got), Err(want)) => assert!(got.contains(want), "{url}: {got}"),
                (got, want) => panic!("{url}: {got:?}, expected {want:?}"),
            }
        }
        let e = Endpoint::parse("https://h/v1/metrics").unwrap();
        assert_eq!(e.to_string(), "https://h:443/v1/metrics");
    }
}
