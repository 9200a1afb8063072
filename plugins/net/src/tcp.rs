//! The `tcp` channel backend: AimRT's frames (`"YT"` + `u32_le` length + body) over one
//! persistent connection per peer, with a heartbeat when idle; a listener on
//! `tcp_options.listen_ip:listen_port` delivers what it receives to the subscribers of
//! each body's uri.
//!
//! Publishing never blocks: each peer has a queue of at most [`QUEUE`] frames and
//! [`QUEUE_BYTES`] bytes drained by its own task; a full queue refuses (and counts) the
//! message. A peer that goes away is reconnected with backoff (0.1 s doubling to 5 s);
//! frames queued meanwhile wait. At shutdown the queues are written out (for at most
//! [`SETTLE`](crate::channel::SETTLE)); what cannot be is counted as lost.
//!
//! A subscriber's shutdown closes each received connection in stages, so that no frame a
//! publisher wrote is lost with it unseen: it stops accepting, ends its sending side
//! (the publisher sees the end and writes its next frames to a new connection), reads and
//! delivers what comes until the publisher closes its side, for at most [`LAST_FRAMES`],
//! and only then closes.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use aimrt_plugin_api::channel::{ChannelBackend, Publication, PublisherInfo, Subscription};
use aimrt_plugin_api::{BackendOptions, Error};
use bytes::Bytes;
use serde::Deserialize;
use tokio::io::AsyncWriteExt;
use tokio::sync::{mpsc, Notify, OwnedSemaphorePermit, Semaphore};

use crate::channel::{body_of, Inbox, Routes, Taken};
use crate::close::{Closer, Closing, Listener, CLOSE_WAIT};
use crate::receiving::{Claim, Receiving, RECEIVING_BYTES};
use crate::wire::{split_frames, tcp_frame, Frame};

/// Frames waiting per peer at most; a full queue refuses the message.
pub(crate) const QUEUE: usize = 1024;
/// Bytes of frames waiting per peer at most: 1 024 frames of up to 10 MiB would be 10 GiB
/// held for a peer that is away.
pub(crate) const QUEUE_BYTES: usize = 256 << 20;
/// The largest frame body received (AimRT's server: 16 MiB).
const MAX_IN: usize = 16 << 20;
/// The largest frame body sent (AimRT's client: 10 MiB).
const MAX_OUT: usize = 10 << 20;
/// An idle connection sends a heartbeat this often (AimRT's).
const HEARTBEAT: Duration = Duration::from_secs(60);
/// A received connection silent this long is closed (AimRT's: 300 s).
const IDLE: Duration = Duration::from_secs(300);
/// Connections received at most: at the limit, a new one closes the one silent longest, so
/// stalled peers never keep a working one out.
pub(crate) const MAX_CONNECTIONS: usize = 4096;
/// Bytes read at a time; a connection holds no buffer while nothing is pending.
const READ_CHUNK: usize = 64 << 10;
/// How long a closing subscriber reads a connection after it ended its own side, for the
/// frames its publisher wrote before it saw the end.
const LAST_FRAMES: Duration = Duration::from_millis(500);

/// `tcp_options` of net_plugin.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct TcpOptions {
    #[serde(default = "loopback")]
    listen_ip: String,
    listen_port: u16,
}

fn loopback() -> String {
    "127.0.0.1".into()
}

/// The backend.
pub(crate) struct TcpChannel {
    options: Option<TcpOptions>,
    location: String,
    routes: OnceLock<Routes>,
    runtime: Mutex<Option<tokio::runtime::Runtime>>,
    handle: Mutex<Option<tokio::runtime::Handle>>,
    peers: Mutex<HashMap<SocketAddr, PeerQueue>>,
    /// Closes the listener and the received connections at shutdown (when listening).
    closer: Mutex<Option<Closer>>,
    /// The received messages and counters (with the send queues' count) and the stop signal.
    shared: Shared,
    /// What the received connections hold of frames on their way, and what it refused.
    receiving: Arc<Receiving>,
}

impl TcpChannel {
    pub(crate) fn new(options: Option<TcpOptions>, location: String) -> TcpChannel {
        TcpChannel {
            options,
            location,
            routes: OnceLock::new(),
            runtime: Mutex::new(None),
            handle: Mutex::new(None),
            peers: Mutex::default(),
            closer: Mutex::default(),
            shared: Shared {
                inbox: Arc::new(Inbox::new("tcp")),
                stop: Arc::default(),
            },
            receiving: Receiving::new(RECEIVING_BYTES, "net_plugin tcp"),
        }
    }

    /// The queue of `addr`, its task started if there is none (or it ended).
    fn peer(&self, addr: SocketAddr, handle: &tokio::runtime::Handle) -> PeerQueue {
        let mut peers = self.peers.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(q) = peers.get(&addr).filter(|q| !q.tx.is_closed()) {
            return q.clone();
        }
        let (tx, rx) = mpsc::channel(QUEUE);
        let q = PeerQueue {
            tx,
            bytes: Arc::new(Semaphore::new(QUEUE_BYTES)),
        };
        handle.spawn(send_to(addr, rx, self.shared.clone()));
        peers.insert(addr, q.clone());
        q
    }
}

impl ChannelBackend for TcpChannel {
    fn type_name(&self) -> &str {
        "tcp"
    }

    fn init(&self, options: &BackendOptions) -> Result<(), Error> {
        let _ = self.routes.set(Routes::parse(options, "tcp")?);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        let runtime = crate::start_runtime(2, "aimrt_tcp", "TCP")?;
        if let Some(o) = self
            .options
            .as_ref()
            .filter(|_| !self.shared.inbox.is_empty())
        {
            let addr = format!("{}:{}", o.listen_ip, o.listen_port);
            let listener = crate::listen_tcp(&*addr)
                .map_err(|e| crate::cannot_listen("tcp", &addr, &e, &self.location))?;
            let bound = listener.local_addr().map_or(addr, |a| a.to_string());
            let listener = {
                let _in = runtime.enter();
                tokio::net::TcpListener::from_std(listener)
                    .map_err(|e| Error::msg(format!("cannot serve TCP on {bound}: {e}")))?
            };
            let closer = Closer::new(MAX_CONNECTIONS);
            runtime.spawn(accept(
                closer.listener(listener),
                self.shared.inbox.clone(),
                closer.closing(),
                self.receiving.clone(),
            ));
            *self.closer.lock().unwrap_or_else(|e| e.into_inner()) = Some(closer);
            tracing::info!(target: "aimrt", "net_plugin: tcp channel listening on {bound}");
        }
        *self.handle.lock().unwrap_or_else(|e| e.into_inner()) = Some(runtime.handle().clone());
        *self.runtime.lock().unwrap_or_else(|e| e.into_inner()) = Some(runtime);
        Ok(())
    }

    fn shutdown(&self) {
        let handle = self.handle.lock().unwrap_or_else(|e| e.into_inner()).take();
        // The queues close: each task writes what waits and ends; one that cannot reach
        // its peer gives up at once and counts what waits as lost. (A subscriber of this
        // process still reads meanwhile.)
        self.peers.lock().unwrap_or_else(|e| e.into_inner()).clear();
        self.shared.stop.notify_waiters();
        if let Some(handle) = handle {
            self.shared.inbox.settle(&handle);
        }
        // Then the received connections: each reads what its publisher still writes,
        // delivered (or refused by a subscriber that has shut down, and counted).
        if let Some(closer) = self.closer.lock().unwrap_or_else(|e| e.into_inner()).take() {
            closer.close(CLOSE_WAIT);
        }
        let runtime = self
            .runtime
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
        if let Some(rt) = runtime {
            rt.shutdown_timeout(Duration::from_secs(2));
        }
        tracing::info!(target: "aimrt", "net_plugin tcp: {}{}", self.shared.inbox.line(), self.receiving.refused_part());
    }

    fn register_publish_type(&self, publisher: &PublisherInfo<'_>) -> Result<(), Error> {
        match self.routes.get() {
            Some(r) => r.register(publisher, "tcp"),
            None => Err(Error::msg("the tcp backend was not initialized")),
        }
    }

    fn subscribe(&self, subscription: Subscription) -> Result<(), Error> {
        if self.options.is_none() {
            return Err(Error::msg(
                "Failed to subscribe: please set tcp listen IP and port in the configuration (net_plugin options: tcp_options: {listen_ip: 127.0.0.1, listen_port: 50060})",
            ));
        }
        self.shared.inbox.subscribe(subscription);
        Ok(())
    }

    fn publish(&self, publication: &Publication<'_>) -> Result<u64, Error> {
        let refuse = |why: String| self.shared.inbox.refuse(why);
        let handle = self
            .handle
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let (Some(routes), Some(handle)) = (self.routes.get(), handle) else {
            return refuse("the tcp backend is not running".into());
        };
        let (targets, uri) = match routes.targets(publication, "tcp") {
            Ok(r) => (r.addrs, r.uri),
            Err(why) => return refuse(why),
        };
        if targets.is_empty() {
            return Ok(0);
        }
        let body = match body_of(publication, uri.as_deref()) {
            Ok(b) => b,
            Err(why) => return refuse(why),
        };
        if body.len() > MAX_OUT {
            return refuse(format!(
                "the message is {} bytes, over the TCP frame limit of {MAX_OUT}",
                body.len()
            ));
        }
        let frame = Bytes::from(tcp_frame(&body));
        let topic = publication.loss_reporter();
        let mut full = Vec::new();
        for &t in targets.iter() {
            // Taken before it is queued: the peer's task may write it at once.
            let taken = self.shared.inbox.take(&topic);
            if let Err(taken) = self.peer(t, &handle).offer(&frame, taken) {
                // Not taken after all: refused below, not lost.
                taken.refused();
                full.push(t);
            }
        }
        if !full.is_empty() {
            return refuse(format!(
                "the send queue to {} is full ({QUEUE} messages or {} MiB wait for a slow or unreachable peer)",
                full.iter().map(ToString::to_string).collect::<Vec<_>>().join(", "),
                QUEUE_BYTES >> 20
            ));
        }
        Ok(aimrt_plugin_api::channel::RECEIVERS_UNKNOWN)
    }
}

/// One peer's task: connect (with backoff), write the queued frames, send a heartbeat when
/// idle, reconnect when the connection breaks; ends when the queue's senders are gone and
/// it is drained, or, if the peer cannot be reached then, counts what is left as lost.
async fn send_to(addr: SocketAddr, mut rx: mpsc::Receiver<Queued>, shared: Shared) {
    let Shared { inbox, stop } = shared;
    let mut backoff = Duration::from_millis(100);
    // A batch a broken connection did not take, and its frames.
    let mut unsent: Option<(Vec<u8>, Vec<Taken>)> = None;
    loop {
        let connect =
            tokio::time::timeout(Duration::from_secs(5), tokio::net::TcpStream::connect(addr));
        // Shutting down with the peer out of reach: what waits is lost (each counted as
        // it is dropped).
        let give_up = |rx: &mut mpsc::Receiver<Queued>, unsent: Option<(Vec<u8>, Vec<Taken>)>| {
            let left = unsent.map_or(0, |(_, taken)| taken.len()) + rx.len();
            rx.close();
            while rx.try_recv().is_ok() {}
            if left > 0 {
                tracing::warn!(target: "aimrt", "net_plugin tcp: {left} messages queued for {addr} are lost: it cannot be reached and the backend is shutting down");
            }
        };
        let Some(outcome) = unless_stopped(&stop, &rx, connect).await else {
            return give_up(&mut rx, unsent);
        };
        let mut stream = match outcome {
            Ok(Ok(s)) => s,
            failed => {
                let why = match failed {
                    Ok(Err(e)) => e.to_string(),
                    _ => "timed out".to_owned(),
                };
                inbox.warn(format_args!(
                    "cannot connect to {addr}: {why}; retrying in {} ms",
                    backoff.as_millis()
                ));
                if unless_stopped(&stop, &rx, tokio::time::sleep(backoff))
                    .await
                    .is_none()
                {
                    return give_up(&mut rx, unsent);
                }
                backoff = (backoff * 2).min(Duration::from_secs(5));
                continue;
            }
        };
        backoff = Duration::from_millis(100);
        let _ = stream.set_nodelay(true);
        loop {
            // What is waiting goes out in one write (up to 256 KiB), not a write a frame.
            let (mut batch, mut frames) = match unsent.take() {
                Some(b) => b,
                None => tokio::select! {
                    next = tokio::time::timeout(HEARTBEAT, rx.recv()) => match next {
                        // Its bytes leave the queue with it (the permit is dropped).
                        Ok(Some((f, taken, _))) => (f.to_vec(), vec![taken]),
                        Ok(None) => return,
                        Err(_) => (b"YT\0\0\0\0".to_vec(), Vec::new()),
                    },
                    // A subscriber sends nothing: readable means it closed the connection
                    // (or sent bytes, which are dropped). Seen while idle, the next frame
                    // waits for a new connection instead of being written into this one
                    // and lost with it.
                    _ = stream.readable() => match stream.try_read(&mut [0; 256]) {
                        Ok(0) => {
                            inbox.warn(format_args!("{addr} closed the connection; reconnecting"));
                            break;
                        }
                        Ok(_) => continue,
                        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => continue,
                        Err(e) => {
                            inbox.warn(format_args!("the connection to {addr} broke: {e}; reconnecting"));
                            break;
                        }
                    },
                },
            };
            while batch.len() < 256 << 10 {
                match rx.try_recv() {
                    Ok((f, taken, _)) => {
                        batch.extend_from_slice(&f);
                        frames.push(taken);
                    }
                    Err(_) => break,
                }
            }
            if let Err(e) = stream.write_all(&batch).await {
                inbox.warn(format_args!(
                    "the connection to {addr} broke: {e}; reconnecting"
                ));
                // What failed is sent again on the next connection (a frame cut midway
                // makes the receiver drop that connection, not misread it).
                if !frames.is_empty() {
                    unsent = Some((batch, frames));
                }
                break;
            }
            Taken::sent_all(frames);
        }
    }
}

/// A frame waiting for its peer, the message it carries, and its bytes' room in the
/// queue (a permit a byte).
type Queued = (Bytes, Taken, OwnedSemaphorePermit);

/// The sending side of a peer's queue, and the room left for bytes in it.
#[derive(Clone)]
struct PeerQueue {
    tx: mpsc::Sender<Queued>,
    bytes: Arc<Semaphore>,
}

impl PeerQueue {
    /// Queues `frame` unless [`QUEUE`] frames or [`QUEUE_BYTES`] bytes wait; a refusal
    /// gives `taken` back.
    fn offer(&self, frame: &Bytes, taken: Taken) -> Result<(), Taken> {
        let Some(room) = u32::try_from(frame.len())
            .ok()
            .and_then(|n| self.bytes.clone().try_acquire_many_owned(n).ok())
        else {
            return Err(taken);
        };
        self.tx
            .try_send((frame.clone(), taken, room))
            .map_err(|e| e.into_inner().1)
    }
}

/// What every peer's task shares with the backend.
#[derive(Clone)]
struct Shared {
    inbox: Arc<Inbox>,
    /// Told at shutdown: a task waiting to connect gives up.
    stop: Arc<Notify>,
}

/// `f`, unless the backend stops (or the queue's senders are gone) first: `None`.
async fn unless_stopped<F: std::future::Future>(
    stop: &Notify,
    rx: &mpsc::Receiver<Queued>,
    f: F,
) -> Option<F::Output> {
    let stopped = stop.notified();
    tokio::pin!(stopped);
    stopped.as_mut().enable();
    if rx.is_closed() {
        return None;
    }
    tokio::select! {
        out = f => Some(out),
        () = stopped => None,
    }
}

/// The received connections: when each last sent something (ms since the listener
/// started) and how to close it.
#[derive(Default)]
struct Conns {
    next: u64,
    open: HashMap<u64, (Arc<AtomicU64>, tokio::task::AbortHandle)>,
}

async fn accept(
    listener: Listener,
    inbox: Arc<Inbox>,
    closing: Closing,
    receiving: Arc<Receiving>,
) {
    let conns = Arc::new(Mutex::new(Conns::default()));
    let epoch = Instant::now();
    let mut evicted = 0u64;
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            () = closing.not_accepting() => break,
        };
        match accepted {
            Ok((stream, from)) => {
                {
                    let mut c = conns.lock().unwrap_or_else(|e| e.into_inner());
                    if c.open.len() >= MAX_CONNECTIONS {
                        let idlest = c
                            .open
                            .iter()
                            .min_by_key(|(_, (last, _))| last.load(Ordering::Relaxed))
                            .map(|(id, _)| *id);
                        if let Some((_, abort)) = idlest.and_then(|id| c.open.remove(&id)) {
                            abort.abort();
                            evicted += 1;
                            inbox.warn(format_args!(
                                "{MAX_CONNECTIONS} connections are open: the one silent longest is closed to accept {from} ({evicted} closed so far)"
                            ));
                        }
                    }
                }
                // A connection closed above gives its permit back as its task ends.
                let Some(slot) = closing.slot().await else {
                    break;
                };
                let mut c = conns.lock().unwrap_or_else(|e| e.into_inner());
                let id = c.next;
                c.next += 1;
                let last = Arc::new(AtomicU64::new(since(epoch)));
                let (inbox, seen, table) = (inbox.clone(), last.clone(), conns.clone());
                let (closing, budget) = (closing.clone(), receiving.clone());
                // Spawned while the table is held: the task removes itself only after this
                // inserts it.
                let task = tokio::spawn(async move {
                    let _slot = slot;
                    let claim = Claim::new(&budget);
                    receive(stream, from, inbox, &seen, epoch, &closing, claim).await;
                    table
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .open
                        .remove(&id);
                });
                c.open.insert(id, (last, task.abort_handle()));
            }
            Err(e) => {
                inbox.warn(format_args!("accepting a connection failed: {e}"));
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
    }
    // Closed before the connections are told to close.
    drop(listener);
}

/// Milliseconds since `epoch`.
fn since(epoch: Instant) -> u64 {
    epoch.elapsed().as_millis() as u64
}

/// Reads one connection's frames until it closes or is silent for [`IDLE`] (either way, a
/// frame it cut is counted), or sends something that is not a frame (counted, and the
/// connection closed). Its buffer is held in `claim`: a buffer that would take the
/// server's connections over their budget closes the connection, its frame counted as
/// received truncated.
async fn receive(
    stream: tokio::net::TcpStream,
    from: SocketAddr,
    inbox: Arc<Inbox>,
    last: &AtomicU64,
    epoch: Instant,
    closing: &Closing,
    mut claim: Claim<'_>,
) {
    let mut buf: Vec<u8> = Vec::new();
    // Set once the subscriber closes: the end of what the publisher may still write.
    let mut last_frames: Option<tokio::time::Instant> = None;
    let closed = closing.closed();
    tokio::pin!(closed);
    loop {
        let readable = match last_frames {
            None => tokio::select! {
                r = tokio::time::timeout(IDLE, stream.readable()) => r,
                () = &mut closed => {
                    // Our side ends (the publisher sees it and stops writing here); its
                    // frames on the way are still read.
                    let _ = socket2::SockRef::from(&stream).shutdown(std::net::Shutdown::Write);
                    last_frames = Some(tokio::time::Instant::now() + LAST_FRAMES);
                    continue;
                }
            },
            Some(by) => tokio::time::timeout_at(by, stream.readable()).await,
        };
        match readable {
            Ok(Ok(())) => {}
            // Silent for IDLE (perhaps in the middle of a frame), broken, or still open
            // LAST_FRAMES after the subscriber closed.
            Ok(Err(_)) | Err(_) => return cut_short(&buf, from, &inbox),
        }
        // The buffer exists only while bytes are pending or arriving. It grows to the
        // frame it holds the header of at once (else by a chunk), held before it does.
        if buf.capacity() - buf.len() < READ_CHUNK {
            let grown = pending_frame(&buf).max(buf.len() + READ_CHUNK);
            if let Err(full) = claim.hold(grown) {
                inbox.stats.truncated.fetch_add(1, Ordering::Relaxed);
                claim.budget().refuse(format_args!(
                    "closing the connection from {from} in the middle of a frame, its {} bytes so far dropped: {full}",
                    buf.len()
                ));
                return;
            }
            buf.reserve_exact(grown - buf.len());
        }
        match stream.try_read_buf(&mut buf) {
            Ok(0) => return cut_short(&buf, from, &inbox),
            Ok(_) => last.store(since(epoch), Ordering::Relaxed),
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => continue,
            Err(_) => return cut_short(&buf, from, &inbox),
        }
        match split_frames(&mut buf, MAX_IN) {
            Ok(frames) => {
                for f in frames {
                    if let Frame::Body(body) = f {
                        inbox.dispatch(&body, from);
                    }
                }
            }
            Err(why) => {
                inbox.stats.malformed.fetch_add(1, Ordering::Relaxed);
                inbox.warn(format_args!("closing the connection from {from}: {why}"));
                return;
            }
        }
        if buf.is_empty() {
            buf = Vec::new();
        } else if buf.capacity() > pending_frame(&buf).max(buf.len()) + 2 * READ_CHUNK {
            // What a larger frame left is more than the next one needs.
            buf.shrink_to(pending_frame(&buf).max(buf.len() + READ_CHUNK));
        }
        let _ = claim.hold(buf.capacity());
    }
}

/// The size of the frame whose header starts `buf`, header included; 0 while the header
/// is incomplete. (The header was checked when the frames before it were split off, or
/// is checked with the next split.)
fn pending_frame(buf: &[u8]) -> usize {
    match buf {
        [b'Y', b'T', a, b, c, d, ..] => {
            6 + u32::from_le_bytes([*a, *b, *c, *d]).min(MAX_IN as u32) as usize
        }
        _ => 0,
    }
}

/// A connection ended with `rest` of a frame read: that message is lost, counted as
/// received truncated.
fn cut_short(rest: &[u8], from: SocketAddr, inbox: &Inbox) {
    if !rest.is_empty() {
        inbox.stats.truncated.fetch_add(1, Ordering::Relaxed);
        inbox.warn(format_args!(
            "the connection from {from} ended in the middle of a frame: its {} bytes so far are dropped",
            rest.len()
        ));
    }
}

#[cfg(test)]
mod tests {
    use std::io::{Read, Write};

    use super::*;

    /// A tcp server on a free port with `budget`: its runtime, inbox, closer and address.
    fn serving(
        budget: Arc<Receiving>,
    ) -> (tokio::runtime::Runtime, Arc<Inbox>, Closer, SocketAddr) {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let inbox = Arc::new(Inbox::new("tcp"));
        let closer = Closer::new(MAX_CONNECTIONS);
        let listener = crate::listen_tcp("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let listener = {
            let _in = rt.enter();
            tokio::net::TcpListener::from_std(listener).unwrap()
        };
        rt.spawn(accept(
            closer.listener(listener),
            inbox.clone(),
            closer.closing(),
            budget,
        ));
        (rt, inbox, closer, addr)
    }

    /// A closing subscriber ends its side of each connection and still reads what the
    /// publisher writes until the publisher closes its side: every frame is read.
    #[test]
    fn a_closing_subscriber_reads_what_comes_until_the_publisher_closes() {
        let (_rt, inbox, closer, addr) = serving(Receiving::new(RECEIVING_BYTES, "net_plugin tcp"));
        let frames = |n: usize| tcp_frame(&body_of_size(5)).repeat(n);
        let mut publisher = std::net::TcpStream::connect(addr).unwrap();
        publisher
            .set_read_timeout(Some(Duration::from_secs(5)))
            .unwrap();
        publisher.write_all(&frames(100)).unwrap();
        let counted = || inbox.stats.unknown_uri.load(Ordering::Relaxed);
        let by = Instant::now() + Duration::from_secs(5);
        while counted() < 100 && Instant::now() < by {
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(counted(), 100);
        let closed = std::thread::spawn(move || closer.close(Duration::from_secs(5)));
        // The subscriber's end arrives; what the publisher writes meanwhile is still read.
        let mut end = [0u8; 16];
        assert_eq!(publisher.read(&mut end).unwrap(), 0, "the subscriber's end");
        publisher.write_all(&frames(100)).unwrap();
        publisher.shutdown(std::net::Shutdown::Write).unwrap();
        assert!(closed.join().unwrap(), "the connection ended");
        assert_eq!(counted(), 200, "every frame written was read");
        assert!(
            std::net::TcpStream::connect(addr).is_err(),
            "still listening"
        );
    }

    /// A body for a topic nobody subscribes to, with a payload of `n` bytes.
    fn body_of_size(n: usize) -> Vec<u8> {
        crate::wire::Body {
            uri: "/channel/nobody/pb%3Ax",
            serialization_type: "pb",
            meta: Default::default(),
            payload: &vec![b'x'; n],
        }
        .encode()
        .unwrap()
    }

    /// Frames arriving on all connections hold at most the server's budget: with one
    /// connection in the middle of a large frame, a second one's large frame would pass
    /// it and closes that connection (counted); once the first frame is whole, the budget
    /// is free again, and small frames pass however full it is.
    #[test]
    fn frames_arriving_on_all_connections_hold_at_most_the_servers_budget() {
        let budget = Receiving::new(3 << 20, "net_plugin tcp");
        let (_rt, inbox, closer, addr) = serving(budget.clone());
        let stat = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let until = |done: &dyn Fn() -> bool, what: &str| {
            let by = Instant::now() + Duration::from_secs(10);
            while !done() {
                assert!(Instant::now() < by, "{what}");
                std::thread::sleep(Duration::from_millis(2));
            }
        };
        let large = tcp_frame(&body_of_size(2 << 20));
        // Half of a 2 MiB frame, then nothing: its whole frame is held.
        let mut first = std::net::TcpStream::connect(addr).unwrap();
        first.write_all(&large[..1 << 20]).unwrap();
        let whole = (2 << 20) - crate::receiving::UNCOUNTED;
        until(&|| budget.held() >= whole, "the first frame held its size");
        // A second 2 MiB frame would pass 3 MiB: that connection is closed.
        let mut second = std::net::TcpStream::connect(addr).unwrap();
        second
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        let _ = second.write_all(&large);
        let mut end = [0u8; 16];
        assert!(
            matches!(second.read(&mut end), Ok(0) | Err(_)),
            "the second is closed"
        );
        until(&|| budget.refused() == 1, "the refusal is counted");
        assert_eq!(
            stat(&inbox.stats.truncated),
            1,
            "its frame counts as truncated"
        );
        // Small frames pass meanwhile.
        let mut small = std::net::TcpStream::connect(addr).unwrap();
        small
            .write_all(&tcp_frame(&body_of_size(1000)).repeat(50))
            .unwrap();
        until(
            &|| stat(&inbox.stats.unknown_uri) == 50,
            "small frames were read",
        );
        // The first frame completes: the budget is free, and a large frame passes.
        first.write_all(&large[1 << 20..]).unwrap();
        until(
            &|| stat(&inbox.stats.unknown_uri) == 51,
            "the first frame was read",
        );
        until(&|| budget.held() == 0, "the budget is given back");
        let mut third = std::net::TcpStream::connect(addr).unwrap();
        third.write_all(&large).unwrap();
        until(
            &|| stat(&inbox.stats.unknown_uri) == 52,
            "a large frame passes again",
        );
        assert_eq!(budget.refused(), 1);
        assert_eq!(
            budget.refused_part(),
            ", 1 refused as they arrived (the server's connections held 3145728 bytes of messages arriving)"
        );
        drop((first, small, third));
        assert!(closer.close(Duration::from_secs(5)));
    }
}
