//! The plugin's zenoh session, its options, the shared-memory pool, and how both backends
//! put a payload (shared memory when asked and possible, else the network buffer).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};

use aimrt_plugin_api::{Error, PluginOptions, RateLimit};
use serde::Deserialize;
use zenoh::pubsub::Publisher;
use zenoh::sample::{SampleKind, SourceInfo};
use zenoh::session::TransportEventsListener;
use zenoh::shm::{
    Defragment, GarbageCollect, PosixShmProviderBackend, ShmProvider, ShmProviderBuilder, ZShmMut,
};
use zenoh::{Session, Wait};

use crate::connect::Connect;

/// A buffer of `len` bytes (at least 1) from `pool`, reclaiming the buffers every receiver
/// has let go of when the pool is full.
///
/// zenoh's `GarbageCollect` policy reclaims them, but tries again only when one reclaimed
/// buffer alone is as large as `len` (zenoh-shm 1.10.2): a publisher whose messages grow
/// by a byte (a longer sequence number in the header) found the pool full, reclaimed
/// hundreds of buffers into one free run, and still fell back to the network. So after it
/// fails, one plain allocation tries the reclaimed space again.
///
/// ```
/// use zenoh::shm::ShmProviderBuilder;
/// use zenoh::Wait;
/// let pool = ShmProviderBuilder::default_backend(1 << 20).wait().unwrap();
/// let buf = aimrt_zenoh::shm_alloc(&pool, 1000).unwrap();
/// assert_eq!(buf.len(), 1000);
/// ```
pub fn shm_alloc(
    pool: &ShmProvider<PosixShmProviderBackend>,
    len: usize,
) -> Result<ZShmMut, zenoh::shm::ZLayoutAllocError> {
    let len = len.max(1);
    pool.alloc(len)
        .with_policy::<GarbageCollect<Defragment>>()
        .wait()
        .or_else(|_| pool.alloc(len).wait())
}

/// The options of zenoh_plugin, AimRT's keys.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohOptions {
    /// A zenoh JSON5 config file; empty: zenoh's defaults (peer mode, multicast scouting).
    #[serde(default)]
    pub native_cfg_path: String,
    /// Appended to every key as `/<limit_domain>`.
    #[serde(default)]
    pub limit_domain: String,
    /// Bytes of the shared-memory pool, created at the first `shm_enabled` publisher.
    #[serde(default = "default_shm_pool_size")]
    pub shm_pool_size: u64,
    /// Accepted for AimRT's configs; every loan here is exactly the payload's size.
    #[serde(default = "default_shm_init_loan_size")]
    pub shm_init_loan_size: u64,
}

fn default_shm_pool_size() -> u64 {
    10 * 1024 * 1024
}

fn default_shm_init_loan_size() -> u64 {
    1024
}

/// Undeclares every subscriber in `subscribers` (a backend's shutdown).
pub(crate) fn undeclare_all(subscribers: &Mutex<Vec<zenoh::pubsub::Subscriber<()>>>) {
    let taken = std::mem::take(&mut *lock(subscribers));
    for s in taken {
        let _ = s.undeclare().wait();
    }
}

/// Calls `on_change` with `publisher`'s matching status (whether zenoh knows a subscriber
/// of its key): before it returns when one matches already, then at each change, a moment
/// after the declaration that changed it arrived. zenoh's matching listener, kept as long
/// as the publisher. `what` names the publisher's use in the error.
pub(crate) fn follow_matching(
    publisher: &Publisher<'static>,
    what: &str,
    on_change: impl Fn(bool) + Send + Sync + 'static,
) -> Result<(), Error> {
    publisher
        .matching_listener()
        .callback(move |status| on_change(status.matching()))
        .background()
        .wait()
        .map_err(|e| {
            Error::msg(format!(
                "cannot follow the {what} of '{}': {}",
                publisher.key_expr(),
                said(&e)
            ))
        })
}

/// Counters the plugin logs at shutdown.
#[derive(Debug, Default)]
pub(crate) struct Stats {
    /// Payloads put (channel messages, requests, answers).
    pub(crate) sent: AtomicU64,
    /// Of those, through shared memory.
    pub(crate) sent_shm: AtomicU64,
    /// Shared memory was asked for but the pool had no room: sent over the network.
    pub(crate) shm_fallbacks: AtomicU64,
    /// Puts zenoh refused.
    pub(crate) put_failed: AtomicU64,
    /// Messages refused before they were put (encoding, layout limits).
    pub(crate) refused: AtomicU64,
    /// Received payloads that are not AimRT's layout.
    pub(crate) malformed: AtomicU64,
    /// Answers for a request id no call here waits for.
    pub(crate) unknown_ids: AtomicU64,
    /// Channel messages put while zenoh knew no subscriber matching their key: they
    /// reached no one (a publisher ahead of its subscribers, or one whose subscribers
    /// left).
    pub(crate) unmatched: AtomicU64,
    /// Channel messages that never arrived here: gaps in their publishers' sequences
    /// ([`crate::sequence`]), counted once whatever the number of module subscriptions.
    pub(crate) lost: AtomicU64,
}

impl Stats {
    pub(crate) fn line(&self) -> String {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        format!(
            "{} payloads sent ({} through shared memory, {} fell back to the network), {} puts failed, {} refused, {} malformed received, {} answers for unknown request ids, {} channel messages published while no subscriber matched, {} channel messages lost on the way here (gaps in their publishers' sequences)",
            g(&self.sent),
            g(&self.sent_shm),
            g(&self.shm_fallbacks),
            g(&self.put_failed),
            g(&self.refused),
            g(&self.malformed),
            g(&self.unknown_ids),
            g(&self.unmatched),
            g(&self.lost)
        )
    }
}

/// Loads a zenoh JSON5 (or YAML) config file as `native_cfg_path` names it; `Err` says
/// what is wrong with it, naming the file.
///
/// ```no_run
/// let config = aimrt_zenoh::load_native_config("./config/zenoh_native_a.json5").unwrap();
/// ```
pub fn load_native_config(path: &str) -> Result<zenoh::Config, String> {
    if !std::path::Path::new(path).is_file() {
        return Err(format!(
            "native_cfg_path '{path}' is not a file (relative paths start at the working directory, {})",
            std::env::current_dir().map_or_else(|_| "?".into(), |d| d.display().to_string())
        ));
    }
    zenoh::Config::from_file(path).map_err(|e| {
        format!(
            "native_cfg_path '{path}' is not a zenoh config zenoh 1.10 accepts: {}",
            in_plain_words(&e.to_string())
        )
    })
}

/// What zenoh said in an error, in plain words ([`in_plain_words`]).
pub(crate) fn said(e: &impl std::fmt::Display) -> String {
    in_plain_words(&e.to_string())
}

/// zenoh's error text for a user: without the source file zenoh appends (` at
/// /…/zenoh-config-1.10.2/src/lib.rs:1484.`), a JSON or JSON5 error as `line L, column C:
/// what` in the words of config errors ("did you mean" for an unknown value), on one
/// line.
fn in_plain_words(zenoh_says: &str) -> String {
    let unplaced = without_source_places(zenoh_says);
    let text = unplaced.trim().trim_end_matches('.');
    // serde's error through zenoh's Debug: `JSON error: Message { msg: "…", location:
    // Some(Location { line: 1, column: 9 }) }`.
    if let Some(rest) = text.strip_prefix("JSON error: Message { msg: \"") {
        if let Some((msg, location)) = rest.split_once("\", location: ") {
            let number = |key: &str| {
                location
                    .split_once(key)
                    .and_then(|(_, n)| n.split(|c: char| !c.is_ascii_digit()).next())
                    .filter(|n| !n.is_empty())
            };
            let what = aimrt_plugin_api::__private::explain_json(&msg.replace("\\\"", "\""));
            return match (number("line: "), number("column: ")) {
                (Some(line), Some(column)) => format!("line {line}, column {column}: {what}"),
                _ => what,
            };
        }
    }
    // pest's (JSON5) report over several lines: ` --> 1:39`, the line, a caret, `= what`.
    if let Some((_, at)) = text.split_once("--> ") {
        let place = at.split_whitespace().next().unwrap_or("");
        if let (Some((line, column)), Some((_, what))) =
            (place.split_once(':'), text.rsplit_once("= "))
        {
            return format!("line {line}, column {column}: {}", what.trim());
        }
    }
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// `text` without zenoh's ` at <file>.rs:<line>` (an absolute path into cargo's
/// registry), wherever they are: at the end, or inside the brackets of a nested error.
fn without_source_places(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(at) = rest.find(" at ") {
        let place_len = rest[at + 4..]
            .find(|c: char| c.is_whitespace() || c == ']' || c == ')')
            .unwrap_or(rest.len() - at - 4);
        let place = &rest[at + 4..at + 4 + place_len];
        let is_source = place
            .trim_end_matches('.')
            .rsplit_once(".rs:")
            .is_some_and(|(_, line)| !line.is_empty() && line.bytes().all(|b| b.is_ascii_digit()));
        out.push_str(&rest[..at]);
        if is_source {
            // Its sentence's full stop goes with it when a bracket closes next.
            rest = &rest[at + 4 + place_len..];
        } else {
            out.push_str(" at ");
            rest = &rest[at + 4..];
        }
    }
    out.push_str(rest);
    out
}

/// How zenoh's errors say that the process has no file descriptor left (EMFILE).
const OUT_OF_FILES: [&str; 3] = ["Too many open files", "os error 24", "OS error 24"];

/// zenoh's log lines, edited where their words mislead ([`aimrt_plugin_api::rewrite_log_lines`]);
/// `false`: not logged.
/// - A link's accept loop ends every failure with "Hint: increase the system open file
///   limit", which stays only where the failure is about open files.
/// - A peer that opened before its `connect` endpoints answered is told that it goes on
///   connecting.
/// - The unix-socket link warns at every try to connect to a socket nobody listens on
///   (zenoh's TCP link retries without a word), and after every connection it makes (its
///   own end has no file name): neither is logged.
pub(crate) fn zenoh_log_line(target: &str, message: &mut String) -> bool {
    const HINT: &str = " Hint: increase the system open file limit.";
    const SCOUTING: &str = "Scouting delay elapsed before start conditions are met.";
    const UNIX_CONNECT: &str = "Can not create a new UnixSocketStream link bound to ";
    if target.starts_with("zenoh::net::runtime") && message == SCOUTING {
        message.truncate(SCOUTING.len() - 1);
        message.push_str(": no peer answered at connect.endpoints within scouting.delay; the session opens now and goes on connecting in the background (expected for the process that starts first)");
        return true;
    }
    if target.starts_with("zenoh_link_unixsock_stream") {
        if let Some(rest) = message.strip_prefix(UNIX_CONNECT) {
            let nobody = ["No such file or directory", "Connection refused"]
                .iter()
                .any(|e| rest.contains(e));
            let unnamed_end = rest.starts_with('"') && rest.ends_with('"');
            return !(nobody || unnamed_end);
        }
    }
    if !target.starts_with("zenoh_link_") {
        return true;
    }
    let Some(what) = message.strip_suffix(HINT) else {
        return true;
    };
    if OUT_OF_FILES.iter().any(|f| what.contains(f)) {
        return true;
    }
    let what = what.trim_end_matches('.');
    *message = format!("accepting a connection failed: {what}");
    true
}

/// What would be right for a session that zenoh could not open, when zenoh's words say.
fn advice(zenoh_says: &str) -> String {
    let socket_taken = zenoh_says.contains("UnixSocketStream listener")
        && zenoh_says.contains("Unable to acquire lock");
    if zenoh_says.contains("Address already in use") || socket_taken {
        "; another process listens on that endpoint (this config started twice?): give each process its own listen endpoint in the native config".into()
    } else if OUT_OF_FILES
        .iter()
        .any(|emfile| zenoh_says.contains(emfile))
    {
        descriptors_advice().unwrap_or_else(|| {
            "; the process has too many files open: raise its limit (`ulimit -n`)".into()
        })
    } else {
        String::new()
    }
}

/// `; the process has N files open, of a limit of M: raise …` when the process has used
/// (nearly) all the file descriptors its limit allows; `None` when it has not, or where
/// the system does not say.
fn descriptors_advice() -> Option<String> {
    let (limit, _) =
        nix::sys::resource::getrlimit(nix::sys::resource::Resource::RLIMIT_NOFILE).ok()?;
    let open = match std::fs::read_dir("/proc/self/fd") {
        // The count includes the descriptor that reads the folder.
        Ok(entries) => entries.count() as u64,
        Err(e) if e.raw_os_error() == Some(nix::libc::EMFILE) => limit,
        Err(_) => return None,
    };
    // A pool or socket that failed has closed what it had opened by now.
    (open + 8 >= limit).then(|| {
        format!("; the process has {open} files open, of a limit of {limit}: raise the limit (`ulimit -n`)")
    })
}

/// Starts zenoh's thread pools (zenoh-runtime's `app`, `acc`, `tx`, `rx` and `net`),
/// which zenoh otherwise starts at their first use, inside `zenoh::open` or later.
///
/// zenoh panics when a pool cannot start (`Failed to init acc`: out of file descriptors
/// or threads). Inside `zenoh::open` that panic unwinds through zenoh's listeners, whose
/// drop panics again, and the process aborts. And tokio, under a pool, waits forever for
/// the workers it started when it cannot start the next. So each pool starts here first,
/// on a helper thread given 5 s: a pool that cannot start is an error that says why, and
/// a session that opens has all of them.
fn start_runtimes() -> Result<(), String> {
    for pool in zenoh_runtime::ZRuntime::iter() {
        aimrt_plugin_api::__private::contain_on_helper(
            "zenoh_start",
            std::time::Duration::from_secs(5),
            move || {
                let _ = &*pool;
            },
        )
        .map_err(|e| {
            let hint = descriptors_advice().unwrap_or_else(|| {
                "; the process may start no more threads (`ulimit -u`), or is out of memory".into()
            });
            format!("zenoh cannot start its thread pool '{pool}' ({e}){hint}")
        })?;
    }
    Ok(())
}

/// The session both backends share.
pub(crate) struct Zenoh {
    /// `None` once closed: dropped, so that zenoh frees what the session holds (its
    /// `/dev/shm` segment among them) once the backends have dropped their publishers and
    /// subscribers too.
    session: RwLock<Option<Session>>,
    pub(crate) limit_domain: String,
    pub(crate) location: String,
    pool_size: u64,
    shm: RwLock<Pool>,
    pub(crate) stats: Stats,
    alarm: RateLimit,
    /// Says when a peer or router connects and when it goes; undeclared before the
    /// session closes, so that our own close is not reported as every peer gone.
    peers: Mutex<Option<TransportEventsListener<()>>>,
}

/// One line when a zenoh peer or router connects (those connected already included) and
/// one when its connection closes: where two machines lose each other, the log says when.
fn follow_peers(session: &Session) -> Result<TransportEventsListener<()>, Error> {
    session
        .info()
        .transport_events_listener()
        .history(true)
        .callback(|event| {
            let t = event.transport();
            match event.kind() {
                SampleKind::Put => {
                    tracing::info!(target: "aimrt", "zenoh_plugin: connected to {} {}", t.whatami(), t.zid())
                }
                SampleKind::Delete => {
                    tracing::info!(target: "aimrt", "zenoh_plugin: {} {} is gone: it closed its session, or nothing came from it for the lease (transport.link.tx.lease, 10 s by default); zenoh connects again when it can", t.whatami(), t.zid())
                }
            }
        })
        .wait()
        .map_err(|e| {
            Error::msg(format!(
                "cannot follow the zenoh session's connections: {}",
                said(&e)
            ))
        })
}

impl Zenoh {
    /// Loads the native config and opens the session; either failing is an error that
    /// names the file and what zenoh said.
    pub(crate) fn open(o: ZenohOptions, options: &PluginOptions) -> Result<Zenoh, Error> {
        let location = options.location();
        let bad = |message: String| options.invalid(message);
        if o.limit_domain.starts_with('/') || o.limit_domain.ends_with('/') {
            return Err(bad(format!(
                "limit_domain '{}' must not start or end with '/'; write e.g. room1/A2",
                o.limit_domain
            )));
        }
        if o.shm_pool_size == 0 {
            return Err(bad("shm_pool_size must be at least 1 byte".into()));
        }
        let config = if o.native_cfg_path.is_empty() {
            zenoh::Config::default()
        } else {
            load_native_config(&o.native_cfg_path).map_err(bad)?
        };
        if !o.limit_domain.is_empty() {
            let probe = format!("channel/<topic>/<type>/{}", o.limit_domain);
            if let Err(e) = zenoh::key_expr::KeyExpr::try_from(probe.clone()) {
                let said = said(&e);
                let why = said.rsplit_once("`: ").map_or(&*said, |(_, why)| why);
                return Err(bad(format!(
                    "limit_domain '{}' does not make valid zenoh keys (as {probe}): {why}",
                    o.limit_domain
                )));
            }
        }
        let connect = Connect::of(&config);
        connect
            .check()
            .map_err(|why| bad(format!("native_cfg_path '{}': {why}", o.native_cfg_path)))?;
        start_runtimes().map_err(|why| {
            Error::msg(format!(
                "Unable to open zenoh session (native_cfg_path '{}'): {why}",
                o.native_cfg_path
            ))
        })?;
        if let Some(line) = connect.waiting() {
            tracing::info!(target: "aimrt", "{line}");
        }
        let session = zenoh::open(config).wait().map_err(|e| {
            let said = e.to_string();
            let plain = in_plain_words(&said);
            let why = connect
                .unreachable(&plain)
                .unwrap_or_else(|| format!("{plain}{}", advice(&said)));
            Error::msg(format!(
                "Unable to open zenoh session (native_cfg_path '{}'): {why}",
                o.native_cfg_path,
            ))
        })?;
        tracing::info!(target: "aimrt", "zenoh_plugin: session {} open as a {} (native_cfg_path '{}', limit_domain '{}')", session.zid(), connect.mode, o.native_cfg_path, o.limit_domain);
        let peers = follow_peers(&session)?;
        Ok(Zenoh {
            session: RwLock::new(Some(session)),
            limit_domain: o.limit_domain,
            location: location.to_owned(),
            pool_size: o.shm_pool_size,
            shm: RwLock::new(Pool::NotAsked),
            stats: Stats::default(),
            alarm: RateLimit::from_millis(1000),
            peers: Mutex::new(Some(peers)),
        })
    }

    /// The session, for declaring on it or a one-off put; `Err` once it is closed.
    pub(crate) fn session(&self) -> Result<Session, Error> {
        read(&self.session)
            .clone()
            .ok_or_else(|| Error::msg("zenoh_plugin: the zenoh session is closed"))
    }

    /// Creates the shared-memory pool (once); an error names the size.
    pub(crate) fn ensure_shm(&self) -> Result<(), Error> {
        let mut pool = write(&self.shm);
        if let Pool::NotAsked = *pool {
            *pool = match ShmProviderBuilder::default_backend(self.pool_size as usize).wait() {
                Ok(p) => Pool::Ready(p),
                Err(e) => {
                    tracing::error!(target: "aimrt", "zenoh_plugin: cannot create a shared-memory pool of {} bytes: {}", self.pool_size, said(&e));
                    Pool::Failed
                }
            };
        }
        match *pool {
            Pool::Ready(_) => Ok(()),
            Pool::Closed => Err(Error::msg("zenoh_plugin: the zenoh session is closed")),
            Pool::NotAsked | Pool::Failed => Err(Error::msg(format!(
                "zenoh_plugin: cannot create a shared-memory pool of shm_pool_size {} bytes (options at {}); lower it or turn shm_enabled off",
                self.pool_size, self.location
            ))),
        }
    }

    /// Logs at most once a second, with how many lines were held back.
    pub(crate) fn warn(&self, what: std::fmt::Arguments<'_>) {
        if let Some(held) = self.alarm.admit() {
            tracing::warn!(target: "aimrt", "zenoh_plugin: {what} ({held} more such lines held back since the last)");
        }
    }

    /// Counts a refused message and says why.
    pub(crate) fn refuse(&self, why: String) -> Error {
        self.stats.refused.fetch_add(1, Ordering::Relaxed);
        Error::msg(why)
    }

    /// Puts `payload` through `publisher`: copied into a shared-memory buffer when `shm`
    /// and the pool has room (else counted and sent over the network). `Err`: zenoh
    /// refused the put.
    pub(crate) fn put(
        &self,
        publisher: &Publisher<'static>,
        payload: Vec<u8>,
        shm: bool,
    ) -> Result<(), String> {
        let payload = match self.shm_buffer(payload.len(), shm) {
            Some(mut buf) => {
                buf.copy_from_slice(&payload);
                Payload::Shm(buf)
            }
            None => Payload::Heap(payload),
        };
        self.send(publisher, payload, None)
    }

    /// Room for `head` and `len` bytes behind it, at the returned offset: a
    /// shared-memory buffer when `shm` and the pool has room (else counted); otherwise
    /// `head` grown within its capacity, or a buffer of `reuse` (no allocation or
    /// zero-fill per message for the large ones). Filled, it goes to
    /// [`send`](Self::send).
    pub(crate) fn room(
        &self,
        mut head: Vec<u8>,
        len: usize,
        shm: bool,
        reuse: &Arc<Buffers>,
    ) -> (Payload, usize) {
        let at = head.len();
        match self.shm_buffer(at + len, shm) {
            Some(mut buf) => {
                buf[..at].copy_from_slice(&head);
                (Payload::Shm(buf), at)
            }
            None if at + len <= head.capacity() => {
                head.resize(at + len, 0);
                (Payload::Heap(head), at)
            }
            None => {
                let mut buf = reuse.take(at + len);
                buf.as_mut()[..at].copy_from_slice(&head);
                (Payload::Reused(buf), at)
            }
        }
    }

    /// Puts a filled payload through `publisher`, with `source` as zenoh's source info
    /// where given. `Err`: zenoh refused the put.
    pub(crate) fn send(
        &self,
        publisher: &Publisher<'static>,
        payload: Payload,
        source: Option<SourceInfo>,
    ) -> Result<(), String> {
        self.put_bytes(publisher, self.bytes(payload), source)
    }

    /// A filled payload as zenoh takes it (counted when it is in shared memory); cloned, it
    /// shares the buffer.
    pub(crate) fn bytes(&self, payload: Payload) -> zenoh::bytes::ZBytes {
        match payload {
            Payload::Shm(buf) => {
                self.stats.sent_shm.fetch_add(1, Ordering::Relaxed);
                buf.into()
            }
            Payload::Heap(bytes) => bytes.into(),
            Payload::Reused(buf) => bytes::Bytes::from_owner(buf).into(),
        }
    }

    /// [`send`](Self::send) of a payload made into [`bytes`](Self::bytes).
    pub(crate) fn put_bytes(
        &self,
        publisher: &Publisher<'static>,
        payload: zenoh::bytes::ZBytes,
        source: Option<SourceInfo>,
    ) -> Result<(), String> {
        match publisher.put(payload).source_info(source).wait() {
            Ok(()) => {
                self.stats.sent.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
            Err(e) => {
                self.stats.put_failed.fetch_add(1, Ordering::Relaxed);
                Err(format!(
                    "zenoh refused the put on '{}': {}",
                    publisher.key_expr(),
                    said(&e)
                ))
            }
        }
    }

    /// A shared-memory buffer of exactly `len` bytes, or `None` when not asked for or
    /// the pool has no room (counted and said).
    fn shm_buffer(&self, len: usize, shm: bool) -> Option<ZShmMut> {
        if !shm {
            return None;
        }
        let pool = read(&self.shm);
        let Pool::Ready(provider) = &*pool else {
            return None;
        };
        match shm_alloc(provider, len) {
            Ok(buf) if buf.len() == len => Some(buf),
            Ok(buf) => {
                self.stats.shm_fallbacks.fetch_add(1, Ordering::Relaxed);
                self.warn(format_args!(
                    "the shared-memory pool gave {} bytes for {len}; sent over the network instead",
                    buf.len()
                ));
                None
            }
            Err(e) => {
                self.stats.shm_fallbacks.fetch_add(1, Ordering::Relaxed);
                self.warn(format_args!(
                    "the shared-memory pool ({} bytes) has no room for {} bytes ({e:?}); sent over the network instead",
                    self.pool_size,
                    len
                ));
                None
            }
        }
    }

    /// Closes the session (once): every subscriber and publisher of it stops. Then drops
    /// it and the shared-memory pool: with the backends' publishers and subscribers
    /// dropped too ([`crate::Release`]), zenoh unmaps and removes their `/dev/shm` files
    /// and closes their descriptors now, not at the next zenoh process's start.
    pub(crate) fn close(&self) {
        let taken = write(&self.session).take();
        let Some(session) = taken else {
            return;
        };
        tracing::info!(target: "aimrt", "zenoh_plugin: {}", self.stats.line());
        drop(lock(&self.peers).take());
        if let Err(e) = session.close().wait() {
            tracing::warn!(target: "aimrt", "zenoh_plugin: closing the session failed: {}", said(&e));
        }
        drop(session);
        *write(&self.shm) = Pool::Closed;
    }
}

/// The shared-memory pool: created at the first `shm_enabled` publisher, dropped when the
/// session closes.
enum Pool {
    NotAsked,
    Failed,
    Ready(ShmProvider<PosixShmProviderBackend>),
    Closed,
}

/// A payload laid out for one put: in a shared-memory buffer, on the heap, or in a
/// buffer that goes back to its publisher's [`Buffers`] once zenoh has sent it.
pub(crate) enum Payload {
    Shm(ZShmMut),
    Heap(Vec<u8>),
    Reused(Reused),
}

impl AsMut<[u8]> for Payload {
    fn as_mut(&mut self) -> &mut [u8] {
        match self {
            Payload::Shm(buf) => buf,
            Payload::Heap(bytes) => bytes,
            Payload::Reused(buf) => buf.as_mut(),
        }
    }
}

/// Heap buffers of one publisher, used again for its later messages: a large message
/// costs no allocation and no zero-fill (the encoder writes every byte of its room; a
/// buffer only ever carries the same publisher's messages). At most [`KEEP`] buffers of
/// at most [`KEEP_BYTES`] each are kept.
#[derive(Debug, Default)]
pub(crate) struct Buffers(Mutex<Vec<Vec<u8>>>);

/// How many buffers a publisher keeps.
const KEEP: usize = 4;
/// The largest buffer kept; a larger one is freed after its send.
const KEEP_BYTES: usize = 4 << 20;

impl Buffers {
    /// A buffer of `len` bytes: a kept one (grown when short), or a new one.
    fn take(self: &Arc<Self>, len: usize) -> Reused {
        let mut buf = lock(&self.0).pop().unwrap_or_default();
        if buf.len() < len {
            buf.resize(len, 0);
        }
        Reused {
            buf,
            len,
            home: self.clone(),
        }
    }
}

/// A poisoned lock is taken as it is: nothing here leaves what it guards torn.
pub(crate) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// [`lock`]'s read side.
pub(crate) fn read<T>(l: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(|e| e.into_inner())
}

/// [`lock`]'s write side.
pub(crate) fn write<T>(l: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    l.write().unwrap_or_else(|e| e.into_inner())
}

/// The first `len` bytes of a kept buffer; back to its [`Buffers`] when dropped.
#[derive(Debug)]
pub(crate) struct Reused {
    buf: Vec<u8>,
    len: usize,
    home: Arc<Buffers>,
}

impl AsRef<[u8]> for Reused {
    fn as_ref(&self) -> &[u8] {
        &self.buf[..self.len]
    }
}

impl AsMut<[u8]> for Reused {
    fn as_mut(&mut self) -> &mut [u8] {
        &mut self.buf[..self.len]
    }
}

impl Drop for Reused {
    fn drop(&mut self) {
        if self.buf.len() > KEEP_BYTES {
            return;
        }
        let mut kept = lock(&self.home.0);
        if kept.len() < KEEP {
            kept.push(std::mem::take(&mut self.buf));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// docs/zenoh.md shows the shutdown line as the plugin writes it, numbers aside.
    #[test]
    fn the_docs_show_the_shutdown_line_as_written() {
        use aimrt_plugin_api::__private::numbers_as_hash;
        let written = numbers_as_hash(&format!("zenoh_plugin: {}", Stats::default().line()));
        let docs =
            std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../docs/zenoh.md"))
                .expect("docs/zenoh.md");
        let shown: Vec<String> = docs
            .lines()
            .filter(|l| l.contains(" payloads sent ("))
            .filter_map(|l| l.find("zenoh_plugin: ").map(|at| &l[at..]))
            .map(|l| numbers_as_hash(l.trim_end_matches(['`', '.'])))
            .collect();
        assert!(!shown.is_empty(), "docs/zenoh.md shows no shutdown line");
        for line in shown {
            assert_eq!(line, written);
        }
    }

    /// What zenoh 1.10 says of a bad native config, as a user reads it.
    #[test]
    fn zenohs_config_errors_read_as_one_line_with_the_place() {
        let dir = std::env::temp_dir().join(format!("aimrt_zenoh_words_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (name, text, says) in [
            (
                "variant",
                r#"{ mode: "peeer" }"#,
                "line 1, column 9: unknown value 'peeer'; did you mean 'peer'?",
            ),
            (
                "cut",
                r#"{ mode: "peer", listen: { endpoints: ["tcp/127.0.0.1:9"] } "#,
                "line 1, column 39: expected",
            ),
        ] {
            let path = dir.join(format!("{name}.json5"));
            std::fs::write(&path, text).unwrap();
            let e = load_native_config(path.to_str().unwrap()).unwrap_err();
            let (_, what) = e.split_once("zenoh 1.10 accepts: ").unwrap();
            assert!(what.starts_with(says), "{name}: {e}");
            assert!(!e.contains('\n') && !e.contains(".rs:"), "{name}: {e}");
        }
        let _ = std::fs::remove_dir_all(&dir);
        assert_eq!(
            in_plain_words("invalid port value at /root/.cargo/registry/src/x/zenoh-link-commons-1.10.2/src/lib.rs:62."),
            "invalid port value"
        );
        // Nested: the place inside the brackets of the inner error.
        assert_eq!(
            in_plain_words("Can not create a new TCP listener bound to tcp/127.0.0.1:7448: [127.0.0.1:7448: Address already in use (os error 98) at /root/.cargo/registry/src/i/zenoh-link-commons-1.10.2/src/tcp.rs:61.]"),
            "Can not create a new TCP listener bound to tcp/127.0.0.1:7448: [127.0.0.1:7448: Address already in use (os error 98)]"
        );
        // " at " that is no source place stays.
        assert_eq!(
            in_plain_words("listening at tcp/127.0.0.1:9 failed"),
            "listening at tcp/127.0.0.1:9 failed"
        );
    }

    #[test]
    fn zenohs_open_files_hint_stays_only_where_it_is_about_open_files() {
        let edited = |target: &str, message: &str| {
            let mut m = message.to_owned();
            assert!(zenoh_log_line(target, &mut m), "{message} is dropped");
            m
        };
        // The unix-socket link's warnings about connecting are not logged; its others are.
        let unix = "zenoh_link_unixsock_stream::unicast";
        for (message, logged) in [
            ("Can not create a new UnixSocketStream link bound to \"/tmp/a.sock\": No such file or directory (os error 2) at zenoh-link-unixsock_stream-1.10.2/src/unicast.rs:248.", false),
            ("Can not create a new UnixSocketStream link bound to \"/tmp/a.sock\": Connection refused (os error 111)", false),
            ("Can not create a new UnixSocketStream link bound to \"/tmp/a.sock\"", false),
            ("Can not create a new UnixSocketStream link bound to \"/tmp/a.sock\": Permission denied (os error 13)", true),
            ("Can not create a new UnixSocketStream listener on /tmp/a.sock - Unable to acquire lock: EAGAIN", true),
        ] {
            let mut m = message.to_owned();
            assert_eq!(zenoh_log_line(unix, &mut m), logged, "{message}");
        }
        assert_eq!(
            edited("zenoh_link_tcp::unicast", "Connection reset by peer (os error 104). Hint: increase the system open file limit."),
            "accepting a connection failed: Connection reset by peer (os error 104)"
        );
        assert_eq!(
            edited("zenoh::net::runtime::orchestrator", "Scouting delay elapsed before start conditions are met."),
            "Scouting delay elapsed before start conditions are met: no peer answered at connect.endpoints within scouting.delay; the session opens now and goes on connecting in the background (expected for the process that starts first)"
        );
        for (target, kept) in [
            (
                "zenoh_link_tcp::unicast",
                "Too many open files (os error 24). Hint: increase the system open file limit.",
            ),
            (
                "zenoh::net::runtime",
                "Connection reset by peer (os error 104). Hint: increase the system open file limit.",
            ),
            (
                "zenoh_link_unixsock_stream::unicast",
                "Scouting delay elapsed before start conditions are met.",
            ),
        ] {
            assert_eq!(edited(target, kept), kept, "{target}");
        }
    }

    #[test]
    fn a_listen_endpoint_another_process_holds_is_said_so() {
        for zenoh_says in [
            "Can not create a new TCP listener bound to tcp/127.0.0.1:7448: [127.0.0.1:7448: Address already in use (os error 98)]",
            "Can not create a new UnixSocketStream listener on /tmp/robot.sock - Unable to acquire lock: EAGAIN: Try again",
        ] {
            assert!(
                advice(zenoh_says).starts_with("; another process listens on that endpoint"),
                "{zenoh_says}"
            );
        }
        assert_eq!(advice("Invalid TLS certificate file"), "");
    }

    fn kept(b: &Buffers) -> Vec<usize> {
        lock(&b.0).iter().map(Vec::len).collect()
    }

    /// A full pool of buffers one byte shorter than the next, all let go of: zenoh's
    /// `GarbageCollect` alone reclaims them and still refuses the longer one (no reclaimed
    /// buffer is as large); [`shm_alloc`] gives it from the reclaimed space.
    #[test]
    fn a_full_pool_of_shorter_buffers_let_go_of_gives_a_longer_one() {
        let fill = |pool: &ShmProvider<PosixShmProviderBackend>| {
            let mut held = Vec::new();
            while let Ok(buf) = pool.alloc(65_635).wait() {
                held.push(buf);
            }
            assert!(held.len() >= 10, "{} buffers", held.len());
            // Dropped: every receiver let go of them, but the pool has not reclaimed them.
        };
        let zenoh_alone = ShmProviderBuilder::default_backend(1 << 20).wait().unwrap();
        fill(&zenoh_alone);
        let refused = zenoh_alone
            .alloc(65_636)
            .with_policy::<GarbageCollect<Defragment>>()
            .wait();
        assert!(
            refused.is_err(),
            "zenoh's policy now reuses the reclaimed space"
        );
        let pool = ShmProviderBuilder::default_backend(1 << 20).wait().unwrap();
        fill(&pool);
        let buf = shm_alloc(&pool, 65_636).expect("room from the reclaimed buffers");
        assert_eq!(buf.len(), 65_636);
        // The rest of the reclaimed space serves the next, longer ones too.
        drop(buf);
        let again: Vec<_> = (0..10).map(|_| shm_alloc(&pool, 65_637)).collect();
        assert!(again.iter().all(Result::is_ok));
    }

    #[test]
    fn a_sent_buffer_comes_back_and_carries_the_next_message_without_a_new_allocation() {
        let buffers = Arc::new(Buffers::default());
        let mut first = buffers.take(1000);
        first.as_mut().fill(7);
        let at = first.as_ref().as_ptr();
        // zenoh holds it as `Bytes` until sent, then drops it: back to the publisher.
        drop(bytes::Bytes::from_owner(first));
        assert_eq!(kept(&buffers), [1000]);
        let mut second = buffers.take(600);
        assert_eq!(second.as_ref().as_ptr(), at, "the same memory");
        assert_eq!(second.as_mut().len(), 600, "room for the message only");
        // A longer message grows the kept buffer.
        assert_eq!(second.as_ref().len(), 600, "what zenoh sends");
        drop(second);
        assert_eq!(buffers.take(2000).as_ref().len(), 2000);
        assert_eq!(kept(&buffers), [2000]);
    }

    #[test]
    fn at_most_keep_buffers_of_at_most_keep_bytes_are_kept() {
        let buffers = Arc::new(Buffers::default());
        let many: Vec<Reused> = (0..KEEP + 2).map(|_| buffers.take(64)).collect();
        drop(many);
        assert_eq!(kept(&buffers).len(), KEEP);
        lock(&buffers.0).clear();
        drop(buffers.take(KEEP_BYTES + 1));
        assert!(
            kept(&buffers).is_empty(),
            "a buffer over KEEP_BYTES is freed"
        );
        drop(buffers.take(KEEP_BYTES));
        assert_eq!(kept(&buffers), [KEEP_BYTES]);
    }
}
