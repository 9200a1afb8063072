//! The `udp` channel backend: one datagram per message, in AimRT's layout
//! ([`crate::wire::Body`]), to every address of the topic's `server_url_list` (or the
//! `udp://` entries of the context's `aimrt-to_addr`); a receiver on
//! `udp_options.listen_ip:listen_port` delivers to the subscribers of the datagram's uri.
//!
//! Unlike AimRT, a message that cannot fit a datagram is refused at publish time, a
//! datagram longer than `max_pkg_size` (read with one spare byte) is counted as truncated
//! instead of decoded, and datagrams the kernel dropped for the receiver are counted
//! ([`KernelDrops`]).

use std::collections::HashMap;
use std::net::{SocketAddr, ToSocketAddrs, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock};
use std::thread::JoinHandle;
use std::time::Duration;

use aimrt_plugin_api::channel::{
    ChannelBackend, LossReporter, Publication, PublisherInfo, Subscription,
};
use aimrt_plugin_api::{BackendOptions, Error, RateLimit};
use serde::Deserialize;

use crate::channel::{body_of, Inbox, Routes};
use crate::wire::MAX_DATAGRAM;

/// `udp_options` of net_plugin.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct UdpOptions {
    #[serde(default = "loopback")]
    listen_ip: String,
    listen_port: u16,
    /// The largest datagram the receiver takes (AimRT's default 1024; at most 65 507).
    #[serde(default = "default_max_pkg_size")]
    max_pkg_size: u32,
}

fn loopback() -> String {
    "127.0.0.1".into()
}

fn default_max_pkg_size() -> u32 {
    1024
}

/// The backend.
pub(crate) struct UdpChannel {
    options: Option<UdpOptions>,
    location: String,
    routes: OnceLock<Routes>,
    inbox: Arc<Inbox>,
    senders: Senders,
    receiver: Mutex<Option<(Arc<AtomicBool>, JoinHandle<()>)>>,
}

/// The sockets messages are sent from. A configured address gets a socket connected to
/// it, made on its first message: the kernel keeps that socket's route, so a send skips
/// the route lookup an unconnected send makes each time. The addresses a message's
/// `aimrt-to_addr` names (any number of them) share one unconnected socket per family.
#[derive(Default)]
struct Senders {
    connected: RwLock<HashMap<SocketAddr, Connected>>,
    v4: OnceLock<UdpSocket>,
    v6: OnceLock<UdpSocket>,
}

/// A socket connected to a configured address.
struct Connected {
    socket: UdpSocket,
    /// The topic of the last datagram the kernel took on it. When nothing listens at the
    /// address, the peer's "port unreachable" for that datagram (or an earlier one) comes
    /// back, and the next send on the socket fails with it instead of sending: the
    /// datagram it answered is lost too, and is counted on this topic.
    last: Mutex<Option<LossReporter>>,
}

/// A send that did not go out.
#[derive(Debug)]
struct Unsent {
    error: std::io::Error,
    /// With [`std::io::ErrorKind::ConnectionRefused`]: the topic of the datagram sent
    /// before on the socket, which the peer's "port unreachable" answered (see
    /// [`Connected::last`]).
    earlier: Option<LossReporter>,
}

impl From<std::io::Error> for Unsent {
    fn from(error: std::io::Error) -> Unsent {
        Unsent {
            error,
            earlier: None,
        }
    }
}

/// How long a send waits for room in the kernel's send buffer (full while the link is
/// slower than the publisher; the kernel rounds it up to its ticks) before the message
/// to that address is counted lost: a datagram of 64 KiB leaves a 100 Mbit/s link in
/// about 5 ms, and a stalled link holds a publisher up for no more than one cycle of a
/// 100 Hz loop.
const SEND_WAIT: Duration = Duration::from_millis(10);

/// An unbound-port socket of `to`'s family, whose sends wait at most [`SEND_WAIT`].
fn socket_for(to: &SocketAddr) -> std::io::Result<UdpSocket> {
    let socket = if to.is_ipv6() {
        UdpSocket::bind("[::]:0")
    } else {
        UdpSocket::bind("0.0.0.0:0")
    }?;
    socket.set_write_timeout(Some(SEND_WAIT))?;
    Ok(socket)
}

impl Senders {
    /// Sends `bytes` of `topic` to `to`, from `to`'s connected socket if `configured`.
    fn send(
        &self,
        bytes: &[u8],
        to: &SocketAddr,
        configured: bool,
        topic: &LossReporter,
    ) -> Result<usize, Unsent> {
        if !configured {
            let shared = if to.is_ipv6() { &self.v6 } else { &self.v4 };
            if shared.get().is_none() {
                // A failure is not kept: the next message tries again.
                let _ = shared.set(socket_for(to)?);
            }
            return match shared.get() {
                Some(socket) => Ok(socket.send_to(bytes, to)?),
                None => Err(std::io::Error::other("no socket to send from").into()),
            };
        }
        if let Some(c) = self
            .connected
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .get(to)
        {
            return c.send(bytes, topic);
        }
        let socket = socket_for(to)?;
        socket.connect(to)?;
        self.connected
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .entry(*to)
            .or_insert(Connected {
                socket,
                last: Mutex::new(None),
            });
        self.send(bytes, to, configured, topic)
    }
}

impl Connected {
    /// Sends `bytes` of `topic`. The lock on [`last`](Self::last) is not held across the
    /// send (which may wait for room in the kernel): a refusal that races another
    /// thread's send may find no topic there, and that earlier loss goes uncounted.
    fn send(&self, bytes: &[u8], topic: &LossReporter) -> Result<usize, Unsent> {
        let last = || self.last.lock().unwrap_or_else(|e| e.into_inner());
        match self.socket.send(bytes) {
            Ok(n) => {
                *last() = Some(topic.clone());
                Ok(n)
            }
            Err(error) if error.kind() == std::io::ErrorKind::ConnectionRefused => Err(Unsent {
                error,
                earlier: last().take(),
            }),
            Err(error) => Err(error.into()),
        }
    }

    /// The topic of the last datagram, when its "port unreachable" came back and no send
    /// heard it (read at shutdown; clears the socket's pending error).
    fn unheard_refusal(&self) -> Option<LossReporter> {
        match self.socket.take_error() {
            Ok(Some(e)) if e.kind() == std::io::ErrorKind::ConnectionRefused => {
                self.last.lock().unwrap_or_else(|e| e.into_inner()).take()
            }
            _ => None,
        }
    }
}

impl UdpChannel {
    pub(crate) fn new(options: Option<UdpOptions>, location: String) -> UdpChannel {
        UdpChannel {
            options,
            location,
            routes: OnceLock::new(),
            inbox: Arc::new(Inbox::new("udp")),
            senders: Senders::default(),
            receiver: Mutex::new(None),
        }
    }
}

impl UdpChannel {
    /// A datagram sent to `to` of `topic` was answered "port unreachable": counted lost
    /// after publish, and no longer as sent.
    fn lost_earlier(&self, topic: &LossReporter, to: &SocketAddr) {
        self.inbox.stats.sent.fetch_sub(1, Ordering::Relaxed);
        self.inbox.lose(
            topic,
            format_args!("nothing listens at {to} (the kernel's \"port unreachable\" for a message sent there before); that message is lost"),
        );
    }
}

impl ChannelBackend for UdpChannel {
    fn type_name(&self) -> &str {
        "udp"
    }

    fn init(&self, options: &BackendOptions) -> Result<(), Error> {
        let _ = self.routes.set(Routes::parse(options, "udp")?);
        if let Some(u) = &self.options {
            if u.max_pkg_size == 0 || u.max_pkg_size as usize > MAX_DATAGRAM {
                return Err(Error::Options {
                    what: format!("options of plugin 'net_plugin' at {}", self.location),
                    message: format!(
                        "udp_options.max_pkg_size must be in 1 ..= {MAX_DATAGRAM}, got {}",
                        u.max_pkg_size
                    ),
                });
            }
        }
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        let Some(u) = &self.options else {
            return Ok(());
        };
        if self.inbox.is_empty() {
            return Ok(());
        }
        let addr = format!("{}:{}", u.listen_ip, u.listen_port);
        let socket = bind_receiver(&addr)
            .map_err(|e| crate::cannot_listen("udp", &addr, &e, &self.location))?;
        let _ = socket.set_read_timeout(Some(Duration::from_millis(100)));
        let bound = socket.local_addr().map_or(addr, |a| a.to_string());
        tracing::info!(target: "aimrt", "net_plugin: udp channel listening on {bound}");
        if let Some(note) = socket2::SockRef::from(&socket)
            .recv_buffer_size()
            .ok()
            .and_then(|granted| capped_buffer(&bound, granted))
        {
            tracing::info!(target: "aimrt", "net_plugin udp: {note}");
        }
        let run = Arc::new(AtomicBool::new(true));
        let receive = Receive {
            socket,
            max: u.max_pkg_size as usize,
            inbox: self.inbox.clone(),
            run: run.clone(),
        };
        let handle = std::thread::Builder::new()
            .name("aimrt_udp_recv".into())
            .spawn(move || receive.run())
            .map_err(|e| Error::msg(format!("cannot start the UDP receiver thread: {e}")))?;
        *self.receiver.lock().unwrap_or_else(|e| e.into_inner()) = Some((run, handle));
        Ok(())
    }

    fn shutdown(&self) {
        let taken = self
            .receiver
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
        if let Some((run, handle)) = taken {
            run.store(false, Ordering::SeqCst);
            let _ = handle.join();
        }
        // A "port unreachable" that no later send heard: the last datagram there is lost.
        for (to, c) in self
            .senders
            .connected
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
        {
            if let Some(earlier) = c.unheard_refusal() {
                self.lost_earlier(&earlier, to);
            }
        }
        tracing::info!(target: "aimrt", "net_plugin udp: {}", self.inbox.line());
    }

    fn register_publish_type(&self, publisher: &PublisherInfo<'_>) -> Result<(), Error> {
        match self.routes.get() {
            Some(r) => r.register(publisher, "udp"),
            None => Err(Error::msg("the udp backend was not initialized")),
        }
    }

    fn subscribe(&self, subscription: Subscription) -> Result<(), Error> {
        if self.options.is_none() {
            return Err(Error::msg(
                "Failed to subscribe: please set udp listen IP and port in the configuration (net_plugin options: udp_options: {listen_ip: 127.0.0.1, listen_port: 50040})",
            ));
        }
        self.inbox.subscribe(subscription);
        Ok(())
    }

    fn publish(&self, publication: &Publication<'_>) -> Result<u64, Error> {
        let refuse = |why: String| self.inbox.refuse(why);
        let Some(routes) = self.routes.get() else {
            return refuse("the udp backend is not initialized".into());
        };
        let route = match routes.targets(publication, "udp") {
            Ok(r) => r,
            Err(why) => return refuse(why),
        };
        if route.addrs.is_empty() {
            return Ok(0);
        }
        let bytes = match body_of(publication, route.uri.as_deref()) {
            Ok(b) => b,
            Err(why) => return refuse(why),
        };
        if bytes.len() > MAX_DATAGRAM {
            return refuse(format!(
                "the message is {} bytes as a datagram, over the UDP limit of {MAX_DATAGRAM}; send it over tcp or http",
                bytes.len()
            ));
        }
        let topic = publication.loss_reporter();
        let mut sent = 0;
        for t in route.addrs.iter() {
            let e = match self.senders.send(&bytes, t, route.configured, &topic) {
                Ok(_) => {
                    sent += 1;
                    continue;
                }
                Err(e) => e,
            };
            match e.error.kind() {
                // A connected socket hears the peer's "port unreachable": for a datagram it
                // sent before, now lost too (no longer counted as sent).
                std::io::ErrorKind::ConnectionRefused => {
                    if let Some(earlier) = e.earlier {
                        self.lost_earlier(&earlier, t);
                    }
                    self.inbox.lose(
                        &topic,
                        format_args!("nothing listens at {t}; the message to it is lost"),
                    );
                }
                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => self.inbox.lose(&topic, format_args!(
                    "the kernel's send buffer stayed full for {} ms (the network to {t} is slower than the publisher); the message to it is lost",
                    SEND_WAIT.as_millis()
                )),
                _ => self.inbox.lose(&topic, format_args!(
                    "sending to {t} failed: {}; the message to it is lost",
                    e.error
                )),
            }
        }
        self.inbox.stats.sent.fetch_add(sent, Ordering::Relaxed);
        Ok(aimrt_plugin_api::channel::RECEIVERS_UNKNOWN)
    }
}

/// The receive buffer the receiving socket asks for, so a burst waits in the kernel while
/// subscribers run (the kernel caps it at `net.core.rmem_max`).
const RECEIVE_BUFFER: usize = 4 << 20;

/// The receiving socket, with a receive buffer of [`RECEIVE_BUFFER`] (or what the kernel
/// allows), that is told with each datagram how many the kernel dropped for it so far
/// (`SO_RXQ_OVFL`, Linux).
fn bind_receiver(addr: &str) -> std::io::Result<UdpSocket> {
    let sa: SocketAddr = addr
        .to_socket_addrs()?
        .next()
        .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::InvalidInput, "no address"))?;
    let socket = socket2::Socket::new(
        socket2::Domain::for_address(sa),
        socket2::Type::DGRAM,
        Some(socket2::Protocol::UDP),
    )?;
    let _ = socket.set_recv_buffer_size(RECEIVE_BUFFER);
    // Without it the drops are still read once, at shutdown (`KernelDrops::read`).
    let _ = nix::sys::socket::setsockopt(&socket, nix::sys::socket::sockopt::RxqOvfl, &1);
    socket.bind(&sa.into())?;
    Ok(socket.into())
}

/// What to tell a user whose receive buffer (`granted`, as the kernel reports it: twice
/// what it allows, for its bookkeeping) is less than [`RECEIVE_BUFFER`] asked for.
fn capped_buffer(at: &str, granted: usize) -> Option<String> {
    (granted < 2 * RECEIVE_BUFFER).then(|| format!(
        "the receive buffer of {at} holds {granted} bytes with the kernel's bookkeeping, not the {} that the {RECEIVE_BUFFER} asked for would: net.core.rmem_max caps it; what a longer burst brings is dropped by the kernel and counted. `sysctl -w net.core.rmem_max={RECEIVE_BUFFER}` lifts the cap",
        2 * RECEIVE_BUFFER
    ))
}

/// Datagrams one receive call takes at most: a burst costs one system call per this many
/// instead of one per datagram.
const BATCH: usize = 32;

/// How long the receiver goes on reading at shutdown what is already queued for it.
const DRAIN: Duration = Duration::from_secs(1);

/// The receiver thread.
struct Receive {
    socket: UdpSocket,
    max: usize,
    inbox: Arc<Inbox>,
    run: Arc<AtomicBool>,
}

/// The headers of one receive call: each datagram's sender and room for its drop count.
type Headers = nix::sys::socket::MultiHeaders<nix::sys::socket::SockaddrStorage>;

fn headers() -> Headers {
    Headers::preallocate(BATCH, Some(nix::cmsg_space!(u32)))
}

impl Receive {
    fn run(self) {
        use nix::sys::socket::MsgFlags;
        // One spare byte tells a datagram that fits from one the kernel cut.
        let mut bufs: [Vec<u8>; BATCH] = std::array::from_fn(|_| vec![0u8; self.max + 1]);
        let mut headers = headers();
        let mut drops = KernelDrops::new(&self.socket);
        while self.run.load(Ordering::SeqCst) {
            // Waits (up to the socket's read timeout) for the first datagram, then takes
            // what else is queued without waiting.
            match self.take(
                &mut bufs,
                &mut headers,
                &mut drops,
                MsgFlags::MSG_WAITFORONE,
            ) {
                Ok(_) | Err(nix::errno::Errno::EAGAIN | nix::errno::Errno::EINTR) => {}
                Err(e) => {
                    self.inbox.warn(format_args!("receiving failed: {e}"));
                    std::thread::sleep(Duration::from_millis(10));
                }
            }
        }
        // What is queued already is delivered (or refused and counted by its topics), not
        // let go with the socket; a sender that never pauses cannot hold shutdown up.
        let until = std::time::Instant::now() + DRAIN;
        while std::time::Instant::now() < until
            && matches!(
                self.take(&mut bufs, &mut headers, &mut drops, MsgFlags::MSG_DONTWAIT),
                Ok(n) if n > 0
            )
        {}
        // Drops after the last datagram read tell no datagram: the kernel's table does.
        drops.catch_up(&self.inbox.stats);
        drops.report(&self.socket, true);
    }

    /// One receive call of up to [`BATCH`] datagrams, each dispatched; how many it took.
    fn take(
        &self,
        bufs: &mut [Vec<u8>; BATCH],
        headers: &mut Headers,
        drops: &mut KernelDrops,
        flags: nix::sys::socket::MsgFlags,
    ) -> nix::Result<usize> {
        use nix::sys::socket::ControlMessageOwned;
        use std::io::IoSliceMut;
        use std::os::fd::AsRawFd;
        let mut slices = bufs.each_mut().map(|b| [IoSliceMut::new(b)]);
        let got = nix::sys::socket::recvmmsg(
            self.socket.as_raw_fd(),
            headers,
            slices.iter_mut(),
            flags,
            None,
        )?;
        let (mut n, mut cut) = (0, false);
        for datagram in got {
            n += 1;
            match datagram.cmsgs() {
                Ok(cmsgs) => {
                    for cmsg in cmsgs {
                        if let ControlMessageOwned::RxqOvfl(now) = cmsg {
                            drops.saw(now, &self.inbox.stats);
                        }
                    }
                }
                // No room for the count: see `KernelDrops`.
                Err(_) => cut = true,
            }
            let from = sender_of(datagram.address.as_ref());
            if datagram.bytes > self.max {
                self.inbox.stats.truncated.fetch_add(1, Ordering::Relaxed);
                self.inbox.warn(format_args!("a datagram from {from} is longer than udp_options.max_pkg_size ({} bytes) and was dropped; raise max_pkg_size (at most {MAX_DATAGRAM})", self.max));
                continue;
            }
            let bytes = datagram.iovs().next().unwrap_or_default();
            self.inbox.dispatch(bytes, from);
        }
        if cut {
            *headers = self::headers();
            drops.catch_up(&self.inbox.stats);
        }
        drops.report(&self.socket, false);
        Ok(n)
    }
}

/// The kernel's count of the datagrams it dropped for the receiving socket (mostly: its
/// buffer was full), read from the datagrams that come after them, and at shutdown from
/// the socket's line of `/proc/net/udp`.
///
/// The kernel writes back, into each header of a receive call, the room its control data
/// took, and it adds the count only once it is not 0. So before the first drop every
/// header's room shrinks to none, and the first datagrams to carry a count arrive cut
/// (`MSG_CTRUNC`). Then, once in the socket's life, the count is read from the table and
/// the headers are made anew; from then on each datagram has a count and the room stays.
/// A datagram queued before that read carries a smaller total than the table's: a total
/// behind the last one seen counts nothing.
struct KernelDrops {
    /// The socket's inode, by which `/proc/net/udp` names it.
    inode: Option<u64>,
    /// The running total last seen (a `u32` in the kernel, so it wraps).
    seen: u32,
    /// Counted and not yet logged.
    unsaid: u64,
    alarm: RateLimit,
}

impl KernelDrops {
    /// The socket is this backend's own, so its count started at 0.
    fn new(socket: &UdpSocket) -> KernelDrops {
        use std::os::fd::AsRawFd;
        use std::os::unix::fs::MetadataExt;
        let inode = std::fs::metadata(format!("/proc/self/fd/{}", socket.as_raw_fd()))
            .ok()
            .map(|m| m.ino());
        KernelDrops {
            inode,
            seen: 0,
            unsaid: 0,
            alarm: RateLimit::from_millis(1000),
        }
    }

    /// The running total `now` (from a datagram or the kernel's table): what is new is
    /// counted.
    fn saw(&mut self, now: u32, stats: &crate::channel::Stats) {
        let new = now.wrapping_sub(self.seen);
        if new == 0 || new > u32::MAX / 2 {
            return;
        }
        self.seen = now;
        stats
            .kernel_dropped
            .fetch_add(u64::from(new), Ordering::Relaxed);
        self.unsaid += u64::from(new);
    }

    /// Counts what the kernel's table shows beyond the last total seen.
    fn catch_up(&mut self, stats: &crate::channel::Stats) {
        if let Some(now) = self.read() {
            self.saw(now, stats);
        }
    }

    /// Logs what was counted since the last line: at most once a second, or `now`.
    fn report(&mut self, socket: &UdpSocket, now: bool) {
        if self.unsaid == 0 || !(now || self.alarm.ready()) {
            return;
        }
        let new = std::mem::take(&mut self.unsaid);
        let at = socket
            .local_addr()
            .map_or_else(|_| "this receiver".into(), |a| a.to_string());
        let buffer = socket2::SockRef::from(socket)
            .recv_buffer_size()
            .map_or_else(
                |_| String::new(),
                |b| format!(" ({b} bytes, the kernel's bookkeeping included)"),
            );
        tracing::warn!(target: "aimrt", "net_plugin udp: the kernel dropped {new} datagrams sent to {at} before they were read: its receive buffer{buffer} was full, as the subscribers fell behind their senders; a longer burst needs a larger buffer (the backend asks for {RECEIVE_BUFFER} bytes, the kernel allows net.core.rmem_max)");
    }

    /// The socket's running total in the kernel's table, `None` where `/proc` does not
    /// show it (no procfs).
    fn read(&self) -> Option<u32> {
        let inode = self.inode?;
        ["/proc/net/udp", "/proc/net/udp6"]
            .iter()
            .find_map(|table| {
                let text = std::fs::read_to_string(table).ok()?;
                drops_of(&text, inode)
            })
    }
}

/// The `drops` of the socket with `inode` in a `/proc/net/udp` table: `sl local_address
/// rem_address st tx_queue:rx_queue tr:tm->when retrnsmt uid timeout inode ref pointer
/// drops`.
fn drops_of(table: &str, inode: u64) -> Option<u32> {
    table.lines().skip(1).find_map(|line| {
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.get(9)?.parse::<u64>().ok()? != inode {
            return None;
        }
        fields.get(12)?.parse().ok()
    })
}

/// The sender of a received datagram (unspecified when the kernel gave none).
fn sender_of(address: Option<&nix::sys::socket::SockaddrStorage>) -> SocketAddr {
    use std::net::{Ipv4Addr, SocketAddrV4, SocketAddrV6};
    if let Some(v4) = address.and_then(|a| a.as_sockaddr_in()) {
        return SocketAddr::V4(SocketAddrV4::from(*v4));
    }
    if let Some(v6) = address.and_then(|a| a.as_sockaddr_in6()) {
        return SocketAddr::V6(SocketAddrV6::from(*v6));
    }
    SocketAddr::V4(SocketAddrV4::new(Ipv4Addr::UNSPECIFIED, 0))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn receiver(at: &str) -> Option<UdpSocket> {
        let s = UdpSocket::bind(at).ok()?;
        s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
        Some(s)
    }

    fn got(r: &UdpSocket) -> Vec<u8> {
        let mut buf = [0u8; 64];
        let n = r.recv(&mut buf).expect("a datagram within 5 s");
        buf[..n].to_vec()
    }

    #[test]
    fn a_datagrams_sender_is_its_v4_or_v6_address_or_unspecified_without_one() {
        use nix::sys::socket::SockaddrStorage;
        for at in ["10.0.0.4:50040", "[fe80::1]:7"] {
            let addr: SocketAddr = at.parse().unwrap();
            assert_eq!(sender_of(Some(&SockaddrStorage::from(addr))), addr);
        }
        assert_eq!(sender_of(None).to_string(), "0.0.0.0:0");
    }

    /// A body nobody subscribes to (counted as for an unknown uri).
    const NOBODYS: &[u8] = b"\x05/nope\x02pb\x00x";

    /// A receiver (`max_pkg_size` 100, running or told to stop) at loopback `at` whose
    /// buffer is cut to the kernel's least when `small`, with `sent` datagrams of
    /// [`NOBODYS`] queued on it before it reads (one of 200 bytes after the first `BATCH`
    /// when `cut_one`), and the socket they came from.
    fn queued_receiver(
        at: &str,
        small: bool,
        running: bool,
        sent: usize,
        cut_one: bool,
    ) -> (Receive, UdpSocket) {
        let socket = bind_receiver(at).unwrap();
        socket
            .set_read_timeout(Some(Duration::from_millis(100)))
            .unwrap();
        if small {
            socket2::SockRef::from(&socket)
                .set_recv_buffer_size(1)
                .unwrap();
        }
        let at = socket.local_addr().unwrap();
        let tx = socket_for(&at).unwrap();
        tx.connect(at).unwrap();
        for k in 0..sent {
            if cut_one && k == BATCH {
                tx.send(&[0u8; 200]).unwrap();
            }
            tx.send(NOBODYS).unwrap();
        }
        let receive = Receive {
            socket,
            max: 100,
            inbox: Arc::new(Inbox::new("udp")),
            run: Arc::new(AtomicBool::new(running)),
        };
        (receive, tx)
    }

    #[test]
    fn a_burst_over_several_batches_is_received_whole_and_a_cut_datagram_counted() {
        // More than one batch, queued before the receiver reads: each counted once; one
        // datagram over max_pkg_size in the middle.
        let sent = BATCH * 2 + 5;
        let (receive, _tx) = queued_receiver("127.0.0.1:0", false, true, sent, true);
        let (inbox, run) = (receive.inbox.clone(), receive.run.clone());
        let thread = std::thread::spawn(move || receive.run());
        let deadline = std::time::Instant::now() + Duration::from_secs(5);
        while inbox.stats.unknown_uri.load(Ordering::Relaxed) < sent as u64
            && std::time::Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(5));
        }
        run.store(false, Ordering::SeqCst);
        thread.join().unwrap();
        assert_eq!(inbox.stats.unknown_uri.load(Ordering::Relaxed), sent as u64);
        assert_eq!(inbox.stats.truncated.load(Ordering::Relaxed), 1);
        assert_eq!(inbox.stats.malformed.load(Ordering::Relaxed), 0);
    }

    /// A receiver whose buffer holds a few is told to stop before it reads: it still reads
    /// what is queued, and the kernel's table says how many of the rest it dropped. Every
    /// datagram is one or the other.
    #[test]
    fn what_is_queued_at_shutdown_is_read_and_what_the_kernel_dropped_counted() {
        queued_at_shutdown("127.0.0.1:0");
    }

    /// The same over IPv6: its socket is in `/proc/net/udp6`.
    #[test]
    fn what_the_kernel_dropped_for_an_ipv6_receiver_is_counted_too() {
        // Machines without IPv6 loopback have nothing to test.
        if bind_receiver("[::1]:0").is_ok() {
            queued_at_shutdown("[::1]:0");
        }
    }

    fn queued_at_shutdown(at: &str) {
        let sent = 500;
        let (receive, _tx) = queued_receiver(at, true, false, sent, false);
        let inbox = receive.inbox.clone();
        receive.run();
        let read = inbox.stats.unknown_uri.load(Ordering::Relaxed);
        let dropped = inbox.stats.kernel_dropped.load(Ordering::Relaxed);
        assert!(read > 0, "the queued datagrams are read at shutdown");
        assert!(
            dropped > 0,
            "a buffer of a few datagrams dropped some of {sent}"
        );
        assert_eq!(read + dropped, sent as u64);
        assert!(inbox.line().ends_with(&format!(
            ", {dropped} dropped by the kernel before they were read"
        )));
    }

    /// While running, the kernel's count comes with the datagram after the drops. It finds
    /// no room for it (the headers' room shrank while no datagram had a count), so the
    /// count is read from the kernel's table then, once, and the headers made anew.
    #[test]
    fn the_kernels_drops_are_counted_from_the_next_datagrams_while_running() {
        let sent = 500;
        let (receive, tx) = queued_receiver("127.0.0.1:0", true, true, sent, false);
        let (inbox, run) = (receive.inbox.clone(), receive.run.clone());
        let thread = std::thread::spawn(move || receive.run());
        let read = || inbox.stats.unknown_uri.load(Ordering::Relaxed);
        let settle = |want: &dyn Fn(u64) -> bool| {
            let deadline = std::time::Instant::now() + Duration::from_secs(5);
            while !want(read()) && std::time::Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(5));
            }
            std::thread::sleep(Duration::from_millis(50));
            read()
        };
        let kept = settle(&|n| n > 0);
        assert!(kept > 0 && kept < sent as u64, "{kept} of {sent} kept");
        tx.send(NOBODYS).unwrap();
        assert_eq!(settle(&|n| n == kept + 1), kept + 1);
        let dropped = inbox.stats.kernel_dropped.load(Ordering::Relaxed);
        run.store(false, Ordering::SeqCst);
        thread.join().unwrap();
        assert_eq!(dropped, sent as u64 - kept, "counted while running");
        assert_eq!(
            inbox.stats.kernel_dropped.load(Ordering::Relaxed),
            dropped,
            "and not again at shutdown"
        );
    }

    #[test]
    fn a_receive_buffer_the_kernel_capped_is_said_with_how_to_lift_the_cap() {
        // 212 992 is a common net.core.rmem_max: the kernel reports twice that.
        let note = capped_buffer("127.0.0.1:50040", 425_984).expect("capped");
        assert!(
            note.starts_with("the receive buffer of 127.0.0.1:50040 holds 425984 bytes")
                && note.ends_with("`sysctl -w net.core.rmem_max=4194304` lifts the cap"),
            "{note}"
        );
        assert_eq!(capped_buffer("127.0.0.1:50040", 2 * RECEIVE_BUFFER), None);
    }

    #[test]
    fn a_sockets_drops_are_read_from_its_line_of_the_kernels_table() {
        let table = "   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode ref pointer drops
  123: 0100007F:9C40 00000000:0000 07 00000000:00000000 00:00000000 00000000  1000        0 4242 2 0000000000000000 17
  124: 0100007F:9C41 00000000:0000 07 00000000:00000000 00:00000000 00000000  1000        0 42 2 0000000000000000 4294967295
";
        assert_eq!(drops_of(table, 4242), Some(17));
        assert_eq!(drops_of(table, 42), Some(u32::MAX));
        assert_eq!(drops_of(table, 7), None);
        assert_eq!(drops_of("header only\n", 4242), None);
        assert_eq!(
            drops_of("h\n 1: a b c d e f g h 4242 i j not-a-number\n", 4242),
            None
        );
        let stats = crate::channel::Stats::default();
        let mut drops = KernelDrops {
            inode: Some(u64::MAX),
            seen: 0,
            unsaid: 0,
            alarm: RateLimit::from_millis(1000),
        };
        assert_eq!(drops.read(), None, "no socket has that inode");
        // A running total: each look counts what is new, across the u32's wrap too; a
        // total behind the last (a datagram queued before the table was read) nothing.
        for now in [5, 5, 9, 7, u32::MAX / 2, u32::MAX - 1, 3, u32::MAX] {
            drops.saw(now, &stats);
        }
        assert_eq!(
            stats.kernel_dropped.load(Ordering::Relaxed),
            u64::from(u32::MAX) + 4
        );
    }

    /// A send never waits longer than SEND_WAIT for a link slower than the publisher.
    #[test]
    fn sending_sockets_wait_at_most_send_wait_for_room() {
        for to in ["127.0.0.1:9", "[::1]:9"] {
            let socket = socket_for(&to.parse().unwrap()).unwrap();
            // The kernel keeps it in its ticks (4 ms at HZ=250), rounded up.
            let wait = socket.write_timeout().unwrap().expect("a send timeout");
            assert!(
                wait >= SEND_WAIT && wait <= SEND_WAIT + Duration::from_millis(10),
                "{to}: {wait:?}"
            );
        }
    }

    #[test]
    fn configured_addresses_get_one_connected_socket_each_and_to_addr_ones_none() {
        let senders = Senders::default();
        let none = LossReporter::default();
        let r = receiver("127.0.0.1:0").unwrap();
        let to = r.local_addr().unwrap();
        for k in 0..3u8 {
            senders.send(&[k], &to, true, &none).unwrap();
            assert_eq!(got(&r), [k]);
        }
        assert_eq!(senders.connected.read().unwrap().len(), 1);
        // Addresses from aimrt-to_addr share the unconnected socket: nothing is kept.
        senders.send(b"x", &to, false, &none).unwrap();
        assert_eq!(got(&r), b"x");
        assert_eq!(senders.connected.read().unwrap().len(), 1);
    }

    #[test]
    fn ipv6_addresses_are_reached_configured_or_not() {
        // Machines without IPv6 loopback have nothing to test.
        let Some(r) = receiver("[::1]:0") else {
            return;
        };
        let to = r.local_addr().unwrap();
        let senders = Senders::default();
        let none = LossReporter::default();
        senders.send(b"c", &to, true, &none).unwrap();
        assert_eq!(got(&r), b"c");
        senders.send(b"u", &to, false, &none).unwrap();
        assert_eq!(got(&r), b"u");
    }

    /// The kernel refuses a send on a connected socket when the peer's "port unreachable"
    /// for an earlier datagram came back: that datagram's topic is handed back with the
    /// refusal (it is lost too), once, and a refused send leaves none to hand back.
    #[test]
    fn a_configured_address_nobody_listens_at_is_refused_with_the_datagram_before() {
        let to = {
            let gone = UdpSocket::bind("127.0.0.1:0").unwrap();
            gone.local_addr().unwrap()
        };
        let senders = Senders::default();
        let topic = LossReporter::default();
        let mut results = Vec::new();
        for _ in 0..40 {
            results.push(match senders.send(b"x", &to, true, &topic) {
                Ok(_) => "sent",
                Err(e) if e.error.kind() == std::io::ErrorKind::ConnectionRefused => {
                    if e.earlier.is_some() {
                        "refused, one before"
                    } else {
                        "refused"
                    }
                }
                Err(e) => panic!("{e:?}"),
            });
            // Time for the "port unreachable" to come back.
            std::thread::sleep(Duration::from_millis(2));
        }
        assert!(
            results.contains(&"refused, one before"),
            "a connected socket hears that nothing listens: {results:?}"
        );
        // Each refusal answers a datagram that went out before it, after any other refusal.
        let mut since_refusal = 1;
        for r in &results {
            match *r {
                "sent" => since_refusal += 1,
                "refused, one before" => {
                    assert!(since_refusal > 0, "{results:?}");
                    since_refusal = 0;
                }
                _ => panic!("a refusal without the datagram it answered: {results:?}"),
            }
        }
    }
}
