//! A server's graceful close, shared by net_plugin's HTTP and TCP servers and
//! grpc_plugin's: at shutdown the listeners close first, then each connection finishes
//! what it took (answers, frames on the way) and closes, and the backend waits a bounded
//! time for that before it stops its threads. A client then learns that the server is
//! going (HTTP/1.1 `Connection: close`, HTTP/2 `GOAWAY`, TCP's end of stream) instead of
//! seeing its connection cut under a request, and one that connects again is refused
//! rather than taken by a listener about to close.
//!
//! ```
//! use std::time::Duration;
//! use aimrt_net::close::Closer;
//!
//! let closer = Closer::new(64); // at most 64 connections at once
//! let closing = closer.closing(); // the server's accept loop and connections watch this
//! // (an accept loop takes its listener as `closer.listener(tokio_listener)`)
//! assert!(!closing.is_closing());
//! // At shutdown: no connection is open, so this returns at once.
//! assert!(closer.close(Duration::from_secs(1)));
//! assert!(closing.is_closing());
//! ```

use std::future::Future;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};

/// The stages of a server: open, then taking no new connections (its listeners are
/// closing), then closing its connections.
const OPEN: u8 = 0;
const NOT_ACCEPTING: u8 = 1;
const CLOSING: u8 = 2;

/// The backend's side: tells the server to close, and waits until it has.
#[derive(Debug)]
pub struct Closer {
    stage: watch::Sender<u8>,
    slots: Arc<Semaphore>,
    max: usize,
    listeners: Arc<AtomicUsize>,
}

/// The server's side, one clone for the accept loop and one for each connection: a
/// permit for each connection served (at most the server's maximum) and the signal to
/// close.
#[derive(Debug, Clone)]
pub struct Closing {
    stage: watch::Receiver<u8>,
    slots: Arc<Semaphore>,
}

/// A server's listener, counted by its [`Closer`] until it is dropped: connections are
/// told to close only once no listener is left to take new ones. (A client whose
/// connection closes goes to connect again; a listener still open but no longer
/// accepting would take that connection into its queue and reset it when it closes,
/// with whatever the client wrote into it.)
#[derive(Debug)]
pub struct Listener {
    listener: tokio::net::TcpListener,
    _counted: Counted,
}

#[derive(Debug)]
struct Counted(Arc<AtomicUsize>);

impl Drop for Counted {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

impl Closer {
    /// A server of `max_connections` connections at once at most.
    pub fn new(max_connections: usize) -> Closer {
        Closer {
            stage: watch::channel(OPEN).0,
            slots: Arc::new(Semaphore::new(max_connections)),
            max: max_connections,
            listeners: Arc::default(),
        }
    }

    /// What the server's accept loop and connections watch.
    pub fn closing(&self) -> Closing {
        Closing {
            stage: self.stage.subscribe(),
            slots: self.slots.clone(),
        }
    }

    /// `listener`, counted until it is dropped.
    pub fn listener(&self, listener: tokio::net::TcpListener) -> Listener {
        self.listeners.fetch_add(1, Ordering::AcqRel);
        Listener {
            listener,
            _counted: Counted(self.listeners.clone()),
        }
    }

    /// Tells the accept loops to stop, waits until their listeners are closed, then tells
    /// every connection to close once the requests it took are answered, and waits
    /// (blocking this thread) until every connection has ended; all of it for `within`
    /// at most. `false` when some were still open then.
    pub fn close(&self, within: Duration) -> bool {
        let by = Instant::now() + within;
        let until = |done: &dyn Fn() -> bool| loop {
            if done() {
                return true;
            }
            if Instant::now() >= by {
                return false;
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        self.stage.send_replace(NOT_ACCEPTING);
        until(&|| self.listeners.load(Ordering::Acquire) == 0);
        self.stage.send_replace(CLOSING);
        until(&|| self.slots.available_permits() >= self.max)
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
            () = self.reached(NOT_ACCEPTING) => None,
            slot = self.slots.clone().acquire_owned() => slot.ok(),
        }
    }

    /// Whether the server is closing (it takes no new connections).
    pub fn is_closing(&self) -> bool {
        *self.stage.borrow() >= NOT_ACCEPTING
    }

    /// Resolves when the server stops taking connections: the accept loop ends.
    pub async fn not_accepting(&self) {
        self.reached(NOT_ACCEPTING).await;
    }

    /// Resolves when the server's connections are to close (its listeners are closed by
    /// then); never when its [`Closer`] is gone without closing.
    pub async fn closed(&self) {
        self.reached(CLOSING).await;
    }

    async fn reached(&self, stage: u8) {
        let mut watched = self.stage.clone();
        if watched.wait_for(|s| *s >= stage).await.is_err() {
            std::future::pending::<()>().await;
        }
    }
}

impl Listener {
    /// The next connection, as [`tokio::net::TcpListener::accept`].
    pub async fn accept(&self) -> std::io::Result<(tokio::net::TcpStream, SocketAddr)> {
        self.listener.accept().await
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
    listener: Listener,
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
            break;
        };
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            () = closing.not_accepting() => break,
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
    // Closed before the connections are told to close.
    drop(listener);
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

    /// Connections are told to close only once the listeners are closed: a client that
    /// connects again as its connection closes is refused, not taken into a listener's
    /// queue and reset with what it wrote.
    #[test]
    fn connections_close_after_the_listeners() {
        let rt = runtime();
        let closer = Closer::new(4);
        let listener = rt
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .unwrap();
        let addr = listener.local_addr().unwrap();
        let listener = closer.listener(listener);
        let closing = closer.closing();
        // An accept loop that takes 100 ms to let its listener go once told.
        let watched = closing.clone();
        rt.spawn(async move {
            watched.not_accepting().await;
            tokio::time::sleep(Duration::from_millis(100)).await;
            drop(listener);
        });
        // A connection that connects again as soon as it is told to close.
        let permit = rt.block_on(closing.slot()).expect("a permit");
        let watched = closing.clone();
        let again = rt.spawn(async move {
            watched.closed().await;
            drop(permit);
            tokio::net::TcpStream::connect(addr).await.map(|_| ())
        });
        assert!(closer.close(Duration::from_secs(5)));
        let again = rt.block_on(again).unwrap();
        assert_eq!(
            again.map_err(|e| e.kind()),
            Err(std::io::ErrorKind::ConnectionRefused)
        );
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
