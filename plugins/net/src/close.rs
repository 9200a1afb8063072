//! A server's graceful close, shared by net_plugin's HTTP server and grpc_plugin's: at
//! shutdown the listener stops, each connection finishes the requests it took (their
//! answers are sent) and then closes, and the backend waits a bounded time for that
//! before it stops its threads. A client then learns that the server is going (HTTP/1.1
//! `Connection: close`, HTTP/2 `GOAWAY`) instead of seeing its connection cut under a
//! request.
//!
//! ```
//! use std::time::Duration;
//! use aimrt_net::close::Closer;
//!
//! let closer = Closer::new(64); // at most 64 connections at once
//! let closing = closer.closing(); // the server's accept loop and connections watch this
//! assert!(!closing.is_closing());
//! // At shutdown: no connection is open, so this returns at once.
//! assert!(closer.close(Duration::from_secs(1)));
//! assert!(closing.is_closing());
//! ```

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};

/// The backend's side: tells the server to close, and waits until it has.
#[derive(Debug)]
pub struct Closer {
    closing: watch::Sender<bool>,
    slots: Arc<Semaphore>,
    max: usize,
}

/// The server's side, one clone for the accept loop and one for each connection: a
/// permit for each connection served (at most the server's maximum) and the signal to
/// close.
#[derive(Debug, Clone)]
pub struct Closing {
    closing: watch::Receiver<bool>,
    slots: Arc<Semaphore>,
}

impl Closer {
    /// A server of `max_connections` connections at once at most.
    pub fn new(max_connections: usize) -> Closer {
        Closer {
            closing: watch::channel(false).0,
            slots: Arc::new(Semaphore::new(max_connections)),
            max: max_connections,
        }
    }

    /// What the server's accept loop and connections watch.
    pub fn closing(&self) -> Closing {
        Closing {
            closing: self.closing.subscribe(),
            slots: self.slots.clone(),
        }
    }

    /// Tells the accept loop to stop and every connection to close once the requests it
    /// took are answered, then waits (blocking this thread) until every connection has
    /// ended, for `within` at most; `false` when some were still open then.
    pub fn close(&self, within: Duration) -> bool {
        self.closing.send_replace(true);
        let by = Instant::now() + within;
        loop {
            if self.slots.available_permits() >= self.max {
                return true;
            }
            if Instant::now() >= by {
                return false;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

impl Closing {
    /// A server of `max_connections` that nothing closes (tests, fuzzing).
    pub fn never(max_connections: usize) -> Closing {
        Closer::new(max_connections).closing()
    }

    /// The permit of one more connection, held while it is served; waits while the
    /// server's maximum are served. `None` once the server closes: accept no more.
    pub async fn slot(&self) -> Option<OwnedSemaphorePermit> {
        tokio::select! {
            biased;
            () = self.closed() => None,
            slot = self.slots.clone().acquire_owned() => slot.ok(),
        }
    }

    /// Whether the server is closing.
    pub fn is_closing(&self) -> bool {
        *self.closing.borrow()
    }

    /// Resolves when the server closes; never when its [`Closer`] is gone without
    /// closing.
    pub async fn closed(&self) {
        let mut closing = self.closing.clone();
        if closing.wait_for(|c| *c).await.is_err() {
            std::future::pending::<()>().await;
        }
    }
}

/// How long a backend's shutdown waits for its server's connections to close.
pub const CLOSE_WAIT: Duration = Duration::from_secs(1);

/// Accepts connections on `listener` until the server closes (or the runtime stops), and
/// serves each with `serve` on a task of its own that holds the connection's permit;
/// while the server's maximum are served, further clients wait in the kernel's accept
/// queue. Answers are small, so Nagle's algorithm is off. A failed accept (out of file
/// descriptors and the like) is retried after 50 ms and logged at most once a second, as
/// `<what>: accepting a connection failed: <why> (n failure(s) since the last report);
/// <advice>`.
pub async fn accept<F, Fut>(
    listener: tokio::net::TcpListener,
    closing: Closing,
    (what, advice): (&'static str, &'static str),
    serve: F,
) where
    F: Fn(tokio::net::TcpStream, SocketAddr) -> Fut,
    Fut: Future<Output = ()> + Send + 'static,
{
    let alarm = aimrt_plugin_api::RateLimit::from_millis(1000);
    loop {
        let Some(slot) = closing.slot().await else {
            return;
        };
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            () = closing.closed() => return,
        };
        match accepted {
            Ok((stream, remote)) => {
                let _ = stream.set_nodelay(true);
                let served = serve(stream, remote);
                tokio::spawn(async move {
                    let _slot = slot;
                    served.await;
                });
            }
            Err(e) => {
                if let Some(held) = alarm.admit() {
                    tracing::warn!(target: "aimrt", "{what}: accepting a connection failed: {e} ({} failure(s) since the last report); {advice}", held + 1);
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn runtime() -> tokio::runtime::Runtime {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap()
    }

    #[test]
    fn close_waits_for_the_connections_then_says_whether_all_ended() {
        let rt = runtime();
        let closer = Closer::new(2);
        let closing = closer.closing();
        // A connection that ends 100 ms after it is told to close.
        let permit = rt.block_on(closing.slot()).expect("a permit");
        let watched = closing.clone();
        rt.spawn(async move {
            watched.closed().await;
            tokio::time::sleep(Duration::from_millis(100)).await;
            drop(permit);
        });
        let t = Instant::now();
        assert!(closer.close(Duration::from_secs(5)));
        assert!(t.elapsed() >= Duration::from_millis(100));
        // No more permits once closed.
        assert!(closing.is_closing());
        assert!(rt.block_on(closing.slot()).is_none());
        // A connection that never ends: `close` gives up after `within`.
        let closer = Closer::new(1);
        let _held = rt.block_on(closer.closing().slot()).expect("a permit");
        let t = Instant::now();
        assert!(!closer.close(Duration::from_millis(50)));
        assert!(t.elapsed() >= Duration::from_millis(50));
    }

    #[test]
    fn a_closing_whose_closer_is_gone_never_closes() {
        let rt = runtime();
        let closing = Closing::never(1);
        let waited = rt.block_on(async {
            tokio::time::timeout(Duration::from_millis(50), closing.closed()).await
        });
        assert!(waited.is_err(), "closed without being told to");
        assert!(!closing.is_closing());
        assert!(rt.block_on(closing.slot()).is_some());
    }
}
