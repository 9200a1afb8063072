//! A small MQTT 3.1.1 broker for mqtt_plugin's tests and for trying its examples on a
//! machine without one (`aimrt_mqtt_test_broker`). Not for production: use mosquitto or
//! EMQX, which the plugin is written for.
//!
//! It takes QoS 0, 1 and 2 from publishers (acknowledging as MQTT says), grants every
//! subscription QoS 0 (so it forwards at QoS 0, which MQTT allows), matches `+` and `#`,
//! and serves shared subscriptions `$share/<group>/<filter>`: one member of a group gets
//! each message, in turn. No retained messages, no persistent sessions, no wills. A
//! client id already connected is taken over by the new connection, as MQTT says.
//! [`Broker::start_tls`] serves `ssl://` clients, with client certificates or without.
//!
//! ```
//! let broker = aimrt_mqtt::test_broker::Broker::start("127.0.0.1:0").unwrap();
//! assert_ne!(broker.addr().port(), 0);
//! ```

use std::collections::HashMap;
use std::io::{Read, Write};

use crate::connection::lock;
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::BytesMut;
use rumqttc::{
    matches, ConnAck, ConnectReturnCode, Packet, PubAck, PubComp, PubRec, Publish, QoS, SubAck,
    SubscribeReasonCode, UnsubAck,
};

/// The largest packet taken (MQTT's limit).
const MAX_PACKET: usize = 268_435_455;

/// A running broker; it stops (closing every connection) when dropped.
pub struct Broker {
    /// Where clients connect: the plain listener, or the TLS front.
    addr: SocketAddr,
    /// The plain listener.
    plain: SocketAddr,
    state: Arc<State>,
    /// The TLS front of [`Broker::start_tls`].
    front: Option<TlsFront>,
}

#[derive(Default)]
struct State {
    inner: Mutex<Inner>,
    next_conn: AtomicU64,
    stopped: AtomicBool,
    /// Messages forwarded to subscribers.
    forwarded: AtomicU64,
    /// Publishes are read and neither acknowledged nor forwarded.
    swallowing: AtomicBool,
}

#[derive(Default)]
struct Inner {
    conns: HashMap<u64, Conn>,
    subs: Vec<Sub>,
    /// Whose turn it is in each shared group (by group and filter).
    turns: HashMap<(String, String), usize>,
}

struct Conn {
    client_id: String,
    stream: Arc<Mutex<TcpStream>>,
}

struct Sub {
    conn: u64,
    filter: String,
    /// The group of a shared subscription.
    group: Option<String>,
}

impl Broker {
    /// Listens on `bind` (`127.0.0.1:0`: a free port) and serves on threads of its own.
    pub fn start(bind: &str) -> std::io::Result<Broker> {
        let listener = TcpListener::bind(bind)?;
        let addr = listener.local_addr()?;
        let state = Arc::new(State::default());
        let accepting = state.clone();
        std::thread::Builder::new()
            .name("mqtt_broker".into())
            .spawn(move || {
                for stream in listener.incoming() {
                    if accepting.stopped.load(Ordering::SeqCst) {
                        break;
                    }
                    let Ok(stream) = stream else { continue };
                    let state = accepting.clone();
                    let _ = std::thread::Builder::new()
                        .name("mqtt_broker_conn".into())
                        .spawn(move || serve(&state, stream));
                }
            })?;
        Ok(Broker {
            addr,
            plain: addr,
            state,
            front: None,
        })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Messages forwarded to subscribers so far.
    pub fn forwarded(&self) -> u64 {
        self.state.forwarded.load(Ordering::Relaxed)
    }

    /// Sends `payload` on `topic` to its subscribers as if a client had published it
    /// (the tests' foreign publisher).
    pub fn inject(&self, topic: &str, payload: &[u8]) {
        route(
            &self.state,
            &Publish::new(topic, QoS::AtMostOnce, payload.to_vec()),
        );
    }

    /// From now on (`true`) publishes are read and neither acknowledged nor forwarded, as a
    /// link that loses what it carries would; `false` ends that.
    pub fn swallow_publishes(&self, on: bool) {
        self.state.swallowing.store(on, Ordering::SeqCst);
    }

    /// Closes every connection (the clients see the broker go away); the broker goes on
    /// accepting new ones.
    pub fn drop_connections(&self) {
        let conns: Vec<Arc<Mutex<TcpStream>>> = lock(&self.state.inner)
            .conns
            .values()
            .map(|c| c.stream.clone())
            .collect();
        for c in conns {
            let _ = lock(&c).shutdown(Shutdown::Both);
        }
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        drop(self.front.take());
        self.state.stopped.store(true, Ordering::SeqCst);
        self.drop_connections();
        // Wakes the accept loop so it sees `stopped`.
        let _ = TcpStream::connect(self.plain);
    }
}

/// The files of a TLS server ([`Broker::start_tls`], [`TlsFront`]): its certificate chain
/// and private key (PEM), and the CAs whose client certificates it requires (mutual TLS),
/// if any.
#[derive(Debug, Clone, Default)]
pub struct TlsFiles {
    /// The server's certificate chain (PEM).
    pub cert: String,
    /// Its private key (PEM).
    pub key: String,
    /// CAs of the client certificates required (PEM); empty: none asked for.
    pub client_ca: String,
}

impl Broker {
    /// As [`start`](Self::start), for `ssl://` clients: a [`TlsFront`] on `bind` hands
    /// each connection's bytes to a plain broker of its own. `Err`: a file that does not
    /// serve.
    pub fn start_tls(bind: &str, files: &TlsFiles) -> std::io::Result<Broker> {
        let mut broker = Broker::start("127.0.0.1:0")?;
        let front = TlsFront::start(bind, files, broker.plain)?;
        broker.addr = front.addr();
        broker.front = Some(front);
        Ok(broker)
    }
}

/// A TLS server on a port of its own that hands each connection's bytes to a plain TCP
/// server (the test broker, or any test's server) and back; it stops when dropped.
pub struct TlsFront {
    addr: SocketAddr,
    stop: Arc<tokio::sync::Notify>,
}

impl TlsFront {
    /// Listens on `bind` with `files`, forwarding to `inner`. `Err`: a file that does not
    /// serve, or an address that cannot be listened on.
    pub fn start(bind: &str, files: &TlsFiles, inner: SocketAddr) -> std::io::Result<TlsFront> {
        let config = server_config(files).map_err(std::io::Error::other)?;
        let listener = TcpListener::bind(bind)?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let stop = Arc::new(tokio::sync::Notify::new());
        let stopped = stop.clone();
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        std::thread::Builder::new()
            .name("tls_front".into())
            .spawn(move || {
                rt.block_on(async move {
                    let Ok(listener) = tokio::net::TcpListener::from_std(listener) else {
                        return;
                    };
                    let acceptor = tokio_rustls::TlsAcceptor::from(config);
                    loop {
                        let stream = tokio::select! {
                            s = listener.accept() => s,
                            () = stopped.notified() => return,
                        };
                        let Ok((stream, _)) = stream else { continue };
                        let acceptor = acceptor.clone();
                        tokio::spawn(async move {
                            let mut tls = match acceptor.accept(stream).into_fallible().await {
                                Ok(tls) => tls,
                                Err((_, stream)) => return refuse(stream).await,
                            };
                            let Ok(mut plain) = tokio::net::TcpStream::connect(inner).await else {
                                return;
                            };
                            let _ = tokio::io::copy_bidirectional(&mut tls, &mut plain).await;
                        });
                    }
                });
            })?;
        Ok(TlsFront { addr, stop })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Drop for TlsFront {
    fn drop(&mut self) {
        self.stop.notify_one();
    }
}

/// Ends a connection whose handshake failed (the alert is sent): what the client sent
/// after it is read until the client closes (at most 1 s), so that closing sends no reset
/// that could overtake the alert.
async fn refuse(mut stream: tokio::net::TcpStream) {
    use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
    let _ = stream.shutdown().await;
    let mut sink = [0u8; 4096];
    let _ = tokio::time::timeout(Duration::from_secs(1), async {
        while matches!(stream.read(&mut sink).await, Ok(n) if n > 0) {}
    })
    .await;
}

fn server_config(files: &TlsFiles) -> Result<Arc<rustls::ServerConfig>, String> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
        .with_safe_default_protocol_versions()
        .map_err(|e| e.to_string())?;
    let builder = if files.client_ca.is_empty() {
        builder.with_no_client_auth()
    } else {
        let mut roots = rustls::RootCertStore::empty();
        let cas = aimrt_pem::certificates("client_ca", &files.client_ca);
        for cert in cas.map_err(|e| e.to_string())? {
            roots.add(cert).map_err(|e| e.to_string())?;
        }
        let verifier =
            rustls::server::WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
                .build()
                .map_err(|e| e.to_string())?;
        builder.with_client_cert_verifier(verifier)
    };
    let (chain, key) = aimrt_pem::certified_key(("cert", &files.cert), ("key", &files.key))
        .map_err(|e| e.to_string())?;
    builder
        .with_single_cert(chain, key)
        .map(Arc::new)
        .map_err(|e| e.to_string())
}

fn send(stream: &Mutex<TcpStream>, packet: &Packet) -> bool {
    let mut out = BytesMut::new();
    if packet.write(&mut out, MAX_PACKET).is_err() {
        return false;
    }
    lock(stream).write_all(&out).is_ok()
}

/// One connection, until it closes.
fn serve(state: &State, stream: TcpStream) {
    let id = state.next_conn.fetch_add(1, Ordering::Relaxed);
    let _ = stream.set_nodelay(true);
    let _ = stream.set_write_timeout(Some(Duration::from_secs(5)));
    let Ok(reader) = stream.try_clone() else {
        return;
    };
    let writer = Arc::new(Mutex::new(stream));
    let mut reader = reader;
    let mut buf = BytesMut::with_capacity(64 * 1024);
    let mut chunk = vec![0u8; 64 * 1024];
    'conn: loop {
        let n = match reader.read(&mut chunk) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        buf.extend_from_slice(&chunk[..n]);
        loop {
            let packet = match Packet::read(&mut buf, MAX_PACKET) {
                Ok(p) => p,
                Err(rumqttc::Error::InsufficientBytes(_)) => break,
                Err(_) => break 'conn,
            };
            if !handle(state, id, &writer, packet) {
                break 'conn;
            }
        }
    }
    let _ = lock(&writer).shutdown(Shutdown::Both);
    let mut inner = lock(&state.inner);
    // A client id taken over by a newer connection is no longer this one's.
    inner.conns.remove(&id);
    inner.subs.retain(|s| s.conn != id);
}

/// Handles one packet; `false` closes the connection.
fn handle(state: &State, id: u64, writer: &Arc<Mutex<TcpStream>>, packet: Packet) -> bool {
    match packet {
        Packet::Connect(c) => {
            let old = {
                let mut inner = lock(&state.inner);
                let old: Vec<u64> = inner
                    .conns
                    .iter()
                    .filter(|(_, conn)| !c.client_id.is_empty() && conn.client_id == c.client_id)
                    .map(|(k, _)| *k)
                    .collect();
                let streams: Vec<_> = old
                    .iter()
                    .filter_map(|k| inner.conns.remove(k))
                    .map(|conn| conn.stream)
                    .collect();
                inner.subs.retain(|s| !old.contains(&s.conn));
                inner.conns.insert(
                    id,
                    Conn {
                        client_id: c.client_id,
                        stream: writer.clone(),
                    },
                );
                streams
            };
            for s in old {
                let _ = lock(&s).shutdown(Shutdown::Both);
            }
            send(
                writer,
                &Packet::ConnAck(ConnAck::new(ConnectReturnCode::Success, false)),
            )
        }
        Packet::Publish(_) if state.swallowing.load(Ordering::SeqCst) => true,
        Packet::Publish(p) => {
            let ack = match p.qos {
                QoS::AtMostOnce => None,
                QoS::AtLeastOnce => Some(Packet::PubAck(PubAck::new(p.pkid))),
                QoS::ExactlyOnce => Some(Packet::PubRec(PubRec::new(p.pkid))),
            };
            route(state, &p);
            ack.is_none_or(|a| send(writer, &a))
        }
        Packet::PubRel(r) => send(writer, &Packet::PubComp(PubComp::new(r.pkid))),
        Packet::Subscribe(s) => {
            let mut codes = Vec::new();
            {
                let mut inner = lock(&state.inner);
                for f in s.filters {
                    let (group, filter) = match f.path.strip_prefix("$share/") {
                        Some(rest) => match rest.split_once('/') {
                            Some((g, f)) => (Some(g.to_owned()), f.to_owned()),
                            None => {
                                codes.push(SubscribeReasonCode::Failure);
                                continue;
                            }
                        },
                        None => (None, f.path),
                    };
                    if !rumqttc::valid_filter(&filter) {
                        codes.push(SubscribeReasonCode::Failure);
                        continue;
                    }
                    inner
                        .subs
                        .retain(|s| !(s.conn == id && s.filter == filter && s.group == group));
                    inner.subs.push(Sub {
                        conn: id,
                        filter,
                        group,
                    });
                    codes.push(SubscribeReasonCode::Success(QoS::AtMostOnce));
                }
            }
            send(writer, &Packet::SubAck(SubAck::new(s.pkid, codes)))
        }
        Packet::Unsubscribe(u) => {
            {
                let mut inner = lock(&state.inner);
                for t in &u.topics {
                    let (group, filter) =
                        match t.strip_prefix("$share/").and_then(|r| r.split_once('/')) {
                            Some((g, f)) => (Some(g.to_owned()), f.to_owned()),
                            None => (None, t.clone()),
                        };
                    inner
                        .subs
                        .retain(|s| !(s.conn == id && s.filter == filter && s.group == group));
                }
            }
            send(writer, &Packet::UnsubAck(UnsubAck::new(u.pkid)))
        }
        Packet::PingReq => send(writer, &Packet::PingResp),
        Packet::Disconnect => false,
        // Acks of what the broker sent: it sends only QoS 0.
        _ => true,
    }
}

/// Forwards `p` at QoS 0 to every plain subscription matching it (once per connection)
/// and to one member of each shared group matching it.
fn route(state: &State, p: &Publish) {
    let targets: Vec<Arc<Mutex<TcpStream>>> = {
        let mut inner = lock(&state.inner);
        let mut conns: Vec<u64> = Vec::new();
        let mut groups: HashMap<(String, String), Vec<u64>> = HashMap::new();
        for s in &inner.subs {
            if !matches(&p.topic, &s.filter) {
                continue;
            }
            match &s.group {
                None => conns.push(s.conn),
                Some(g) => groups
                    .entry((g.clone(), s.filter.clone()))
                    .or_default()
                    .push(s.conn),
            }
        }
        for (key, members) in groups {
            let turn = inner.turns.entry(key).or_default();
            conns.push(members[*turn % members.len()]);
            *turn = turn.wrapping_add(1);
        }
        conns.sort_unstable();
        conns.dedup();
        conns
            .iter()
            .filter_map(|c| inner.conns.get(c).map(|c| c.stream.clone()))
            .collect()
    };
    let forward = Packet::Publish(Publish::from_bytes(
        p.topic.clone(),
        QoS::AtMostOnce,
        p.payload.clone(),
    ));
    for t in targets {
        if send(&t, &forward) {
            state.forwarded.fetch_add(1, Ordering::Relaxed);
        } else {
            let _ = lock(&t).shutdown(Shutdown::Both);
        }
    }
}
