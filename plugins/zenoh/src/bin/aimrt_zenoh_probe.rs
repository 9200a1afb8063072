//! A raw zenoh peer for tests and benchmarks: it uses only the `zenoh` crate and AimRT's
//! payload layout, never the plugin.
//!
//! ```text
//! aimrt_zenoh_probe inject <native_cfg.json5> <key>   put malformed payloads, then one valid
//!                                                      ExampleEventMsg{"after garbage", 7}
//! aimrt_zenoh_probe call <native_cfg.json5> <limit_domain> <request hex>
//!                                                      send an AimRT request (e.g. a capture)
//!                                                      with `/<limit_domain>` added to its
//!                                                      pattern; print "answer status=<s>
//!                                                      id=<hex> body=<hex>" (10 s at most)
//! aimrt_zenoh_probe listen <native_cfg.json5> <key> <n>
//!                                                      print "sample <bytes> sn=<n|none>
//!                                                      shm=<bool>" for each of n samples (the
//!                                                      sequence number of zenoh's source
//!                                                      info; 60 s at most)
//! aimrt_zenoh_probe put <native_cfg.json5> <key> <hex>   put one payload as given
//! aimrt_zenoh_probe sequence <native_cfg.json5> <key> <[p:]sn,…>
//!                                                      put ExampleEventMsg{"sn <sn>", sn} with
//!                                                      zenoh's source info: publisher p (0
//!                                                      or 1, default 0) and sequence number
//!                                                      sn, in the order given
//! aimrt_zenoh_probe pong <native_cfg.json5> <ping_key> <pong_key> <shm 0|1> <bytes|typed>
//!                                                      put every sample of ping_key on pong_key
//!                                                      (the raw baseline's echo; runs until killed)
//! aimrt_zenoh_probe ping <native_cfg.json5> <ping_key> <pong_key> <size> <n> <samples> <shm 0|1> <bytes|typed>
//!                                                      the raw baseline's measurement: n
//!                                                      messages, at most 64 unanswered, then
//!                                                      `samples` round trips one at a time;
//!                                                      prints `measuring` and `measured`
//!                                                      around the first phase, then one
//!                                                      JSON line (rate, round trips, and
//!                                                      `stalls`: the first phase's waits for
//!                                                      room in the window of 0.9 ms or more)
//! ```
//!
//! `bytes`: the pong puts the received payload again and the ping puts the same bytes every
//! time and only counts echoes. `typed`: both do what an application carrying
//! `ExampleEventMsg` in AimRT's layout does, as the runtime does for a module: the ping
//! encodes the message into each payload it puts and decodes each echo; the pong decodes
//! each message and encodes it into the payload it puts (into the shared-memory buffer
//! itself when there is a pool). Each typed put also carries zenoh's source info with a
//! sequence number, as the plugin's publisher does by default (`send_sequence`), so the
//! two put the same zenoh message on the wire.
//!
//! `ping` reads two environment variables, for measuring how the round trip rate answers
//! to work on the ping side (benches/scripts/zenoh-sensitivity.sh): `AIMRT_PROBE_SEND_SPIN_NS`
//! and `AIMRT_PROBE_RECV_SPIN_NS`, nanoseconds of busy work after each put and in each
//! echo's callback (default 0; another value than a count of nanoseconds is an error,
//! exit 1).
//!
//! It sets glibc's allocator as `aimrt_main` does (`keep_freed_memory`: large buffers
//! from the heap, freed memory kept), so the raw baseline and ours differ in zenoh and the
//! plugin alone. It exits 0 when done, 1 on a usage or session error, 2 when `listen`
//! timed out.

use std::time::{Duration, Instant};

use aimrt_zenoh::wire::{decode_request, decode_response, encode_request, ChannelPayload};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

fn main() {
    // glibc's allocator set as `aimrt_main` sets it, so that a benchmark compares zenoh
    // with the plugin, not two allocator settings (1 MiB buffers fault in fresh pages
    // each time without it).
    let _ = aimrt_plugin_api::ffi::keep_freed_memory();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let code = match args.iter().map(String::as_str).collect::<Vec<_>>()[..] {
        ["inject", cfg, key] => inject(cfg, key),
        ["call", cfg, domain, hex] => call(cfg, domain, hex),
        ["put", cfg, key, hex] => put_hex(cfg, key, hex),
        ["sequence", cfg, key, list] => match sequence_of(list) {
            Some(list) => sequence(cfg, key, &list),
            None => usage(),
        },
        ["pong", cfg, ping_key, pong_key, shm, mode] => match Mode::parse(mode) {
            Some(mode) => pong(cfg, ping_key, pong_key, shm == "1", mode),
            None => usage(),
        },
        ["ping", cfg, ping_key, pong_key, size, n, samples, shm, mode] => {
            match (size.parse(), n.parse(), samples.parse(), Mode::parse(mode)) {
                (Ok(size), Ok(n), Ok(samples), Some(mode)) => {
                    let keys = (ping_key, pong_key);
                    ping(cfg, keys, size, n, samples, shm == "1", mode)
                }
                _ => usage(),
            }
        }
        ["listen", cfg, key, n] => match n.parse() {
            Ok(n) => listen(cfg, key, n),
            Err(_) => usage(),
        },
        _ => usage(),
    };
    std::process::exit(code);
}

fn usage() -> i32 {
    eprintln!(
        "usage: aimrt_zenoh_probe inject <native_cfg.json5> <key>\n       aimrt_zenoh_probe call <native_cfg.json5> <limit_domain> <request hex>\n       aimrt_zenoh_probe put <native_cfg.json5> <key> <hex>\n       aimrt_zenoh_probe sequence <native_cfg.json5> <key> <[p:]sn,...>\n       aimrt_zenoh_probe listen <native_cfg.json5> <key> <n>\n       aimrt_zenoh_probe pong <native_cfg.json5> <ping_key> <pong_key> <shm 0|1> <bytes|typed>\n       aimrt_zenoh_probe ping <native_cfg.json5> <ping_key> <pong_key> <size> <n> <samples> <shm 0|1> <bytes|typed>"
    );
    1
}

fn open(cfg: &str) -> Option<zenoh::Session> {
    let config = match zenoh::Config::from_file(cfg) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("{cfg}: {e}");
            return None;
        }
    };
    match zenoh::open(config).wait() {
        Ok(s) => Some(s),
        Err(e) => {
            eprintln!("cannot open a zenoh session: {e}");
            None
        }
    }
}

/// `ExampleEventMsg { msg, num }` in protobuf.
fn event_pb(msg: &str, num: i32) -> Vec<u8> {
    use prost::Message as _;
    ExampleEventMsg {
        msg: msg.to_owned(),
        num,
    }
    .encode_to_vec()
}

/// The malformed payloads, each with what is wrong with it.
fn malformed() -> Vec<(&'static str, Vec<u8>)> {
    let valid = ChannelPayload {
        serialization_type: "pb".into(),
        meta: vec![("k".into(), "v".into())],
        message: event_pb("garbage", 1),
    }
    .encode()
    .expect("a small payload");
    let mut long_prefix = valid.clone();
    long_prefix[..4].copy_from_slice(&1_000_000u32.to_le_bytes());
    let mut long_meta = valid.clone();
    // The meta key length says 60 000 bytes.
    long_meta[8..10].copy_from_slice(&60_000u16.to_le_bytes());
    vec![
        ("empty", Vec::new()),
        ("three bytes", vec![1, 2, 3]),
        ("truncated", valid[..valid.len() / 2].to_vec()),
        ("length prefix beyond the payload", long_prefix),
        ("meta longer than the payload", long_meta),
        (
            "unknown serialization type",
            ChannelPayload {
                serialization_type: "xml".into(),
                meta: Vec::new(),
                message: b"<msg/>".to_vec(),
            }
            .encode()
            .expect("a small payload"),
        ),
        (
            "not a protobuf message",
            ChannelPayload {
                serialization_type: "pb".into(),
                meta: Vec::new(),
                message: vec![0xff, 0xff, 0xff],
            }
            .encode()
            .expect("a small payload"),
        ),
        (
            "garbage",
            (0..200u32).map(|i| (i * 37 % 251) as u8).collect(),
        ),
    ]
}

fn inject(cfg: &str, key: &str) -> i32 {
    let Some(session) = open(cfg) else { return 1 };
    let publisher = match session
        .declare_publisher(key.to_owned())
        .congestion_control(CongestionControl::Block)
        .wait()
    {
        Ok(p) => p,
        Err(e) => {
            eprintln!("cannot declare a publisher on {key}: {e}");
            return 1;
        }
    };
    let payloads = malformed();
    for (what, bytes) in &payloads {
        if let Err(e) = publisher.put(bytes.clone()).wait() {
            eprintln!("put '{what}' failed: {e}");
            return 1;
        }
    }
    let valid = ChannelPayload {
        serialization_type: "pb".into(),
        // A peer cannot name the backend: the subscriber sees `zenoh`.
        meta: vec![
            ("probe".into(), "after-garbage".into()),
            ("aimrt-backend".into(), "forged".into()),
        ],
        message: event_pb("after garbage", 7),
    }
    .encode()
    .expect("a small payload");
    if let Err(e) = publisher.put(valid).wait() {
        eprintln!("put of the valid payload failed: {e}");
        return 1;
    }
    println!(
        "injected {} malformed payloads and 1 valid one",
        payloads.len()
    );
    // Let the samples leave before the session closes.
    std::thread::sleep(Duration::from_millis(500));
    let _ = session.close().wait();
    0
}

/// `[p:]sn,…` as (publisher, sequence number) pairs; `None`: not that form.
fn sequence_of(list: &str) -> Option<Vec<(usize, u32)>> {
    list.split(',')
        .map(|item| match item.split_once(':') {
            Some((p, sn)) => Some((p.parse().ok().filter(|p| *p < 2)?, sn.parse().ok()?)),
            None => Some((0, item.parse().ok()?)),
        })
        .collect()
}

fn sequence(cfg: &str, key: &str, list: &[(usize, u32)]) -> i32 {
    use zenoh::sample::SourceInfo;
    let Some(session) = open(cfg) else { return 1 };
    let mut publishers = Vec::new();
    for _ in 0..2 {
        match session
            .declare_publisher(key.to_owned())
            .congestion_control(CongestionControl::Block)
            .wait()
        {
            Ok(p) => publishers.push(p),
            Err(e) => {
                eprintln!("cannot declare a publisher on {key}: {e}");
                return 1;
            }
        }
    }
    for &(p, sn) in list {
        let payload = ChannelPayload {
            serialization_type: "pb".into(),
            meta: vec![],
            message: event_pb(&format!("sn {sn}"), sn as i32),
        }
        .encode()
        .expect("a small payload");
        let publisher = &publishers[p];
        let source = SourceInfo::new(publisher.id(), sn);
        if let Err(e) = publisher.put(payload).source_info(source).wait() {
            eprintln!("put of {p}:{sn} failed: {e}");
            return 1;
        }
    }
    println!("put {} messages", list.len());
    std::thread::sleep(Duration::from_millis(500));
    let _ = session.close().wait();
    0
}

fn listen(cfg: &str, key: &str, n: usize) -> i32 {
    let Some(session) = open(cfg) else { return 1 };
    let subscriber = match session.declare_subscriber(key.to_owned()).wait() {
        Ok(s) => s,
        Err(e) => {
            eprintln!("cannot declare a subscriber on {key}: {e}");
            return 1;
        }
    };
    println!("listening on {key}");
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut seen = 0;
    while seen < n {
        let left = deadline.saturating_duration_since(Instant::now());
        match subscriber.recv_timeout(left) {
            Ok(Some(sample)) => {
                let shm = sample.payload().as_shm().is_some();
                let sn = sample
                    .source_info()
                    .map_or("none".to_owned(), |s| s.source_sn().to_string());
                println!("sample {} sn={sn} shm={shm}", sample.payload().len());
                seen += 1;
            }
            Ok(None) | Err(_) => {
                eprintln!("timed out after {seen} of {n} samples");
                return 2;
            }
        }
    }
    let _ = session.close().wait();
    0
}

fn unhex(text: &str) -> Option<Vec<u8>> {
    (0..text.len() / 2)
        .map(|i| u8::from_str_radix(text.get(2 * i..2 * i + 2)?, 16).ok())
        .collect()
}

fn put_hex(cfg: &str, key: &str, text: &str) -> i32 {
    let Some(bytes) = unhex(text) else {
        eprintln!("the payload is not hex");
        return 1;
    };
    let Some(session) = open(cfg) else { return 1 };
    if let Err(e) = session
        .put(key.to_owned(), bytes)
        .congestion_control(CongestionControl::Block)
        .wait()
    {
        eprintln!("put failed: {e}");
        return 1;
    }
    println!("put done");
    std::thread::sleep(Duration::from_millis(500));
    let _ = session.close().wait();
    0
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn call(cfg: &str, domain: &str, request_hex: &str) -> i32 {
    let mut request = match unhex(request_hex).as_deref().map(decode_request) {
        Some(Ok(r)) => r,
        _ => {
            eprintln!("the request is not hex of AimRT's request layout");
            return 1;
        }
    };
    if !domain.is_empty() {
        request.reply_to = format!("{}/{domain}", request.reply_to);
    }
    let Some(session) = open(cfg) else { return 1 };
    let answers = match session
        .declare_subscriber(format!("rsp/{}", request.reply_to))
        .wait()
    {
        Ok(s) => s,
        Err(e) => {
            eprintln!("cannot subscribe to the answers: {e}");
            return 1;
        }
    };
    let payload = encode_request(&request).expect("a request that decoded encodes");
    if let Err(e) = session
        .put(format!("req/{}", request.reply_to), payload)
        .congestion_control(CongestionControl::Block)
        .wait()
    {
        eprintln!("put failed: {e}");
        return 1;
    }
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match answers.recv_timeout(left) {
            Ok(Some(sample)) => match decode_response(&sample.payload().to_bytes()) {
                Ok(r) if r.req_id == request.req_id => {
                    println!(
                        "answer status={} id={} body={}",
                        r.status,
                        hex(&r.req_id),
                        hex(&r.body)
                    );
                    let _ = session.close().wait();
                    return 0;
                }
                Ok(_) => continue,
                Err(e) => {
                    println!("malformed answer: {e}");
                    return 1;
                }
            },
            Ok(None) | Err(_) => {
                eprintln!("no answer within 10 s");
                return 2;
            }
        }
    }
}

/// What the baseline's two sides do with a message (the crate docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Bytes,
    Typed,
}

impl Mode {
    fn parse(text: &str) -> Option<Mode> {
        match text {
            "bytes" => Some(Mode::Bytes),
            "typed" => Some(Mode::Typed),
            _ => None,
        }
    }
}

/// A baseline side's puts: with zenoh's source info and the next sequence number in
/// `typed` mode, as the plugin's publisher puts a topic with `send_sequence` (its
/// default); plain puts in `bytes` mode.
struct Numbered {
    next_sn: Option<std::sync::atomic::AtomicU32>,
}

impl Numbered {
    fn new(mode: Mode) -> Numbered {
        Numbered {
            next_sn: (mode == Mode::Typed).then(|| std::sync::atomic::AtomicU32::new(0)),
        }
    }

    fn put(
        &self,
        publisher: &zenoh::pubsub::Publisher<'_>,
        payload: zenoh::bytes::ZBytes,
    ) -> zenoh::Result<()> {
        use std::sync::atomic::Ordering;
        let put = publisher.put(payload);
        match &self.next_sn {
            Some(next) => {
                let sn = next.fetch_add(1, Ordering::Relaxed);
                put.source_info(zenoh::sample::SourceInfo::new(publisher.id(), sn))
                    .wait()
            }
            None => put.wait(),
        }
    }
}

/// `aimrt.protocols.example.ExampleEventMsg`, as prost generates it for the runtime's
/// modules (`protocols/`).
#[derive(Clone, PartialEq, prost::Message)]
struct ExampleEventMsg {
    #[prost(string, tag = "1")]
    msg: String,
    #[prost(int32, tag = "2")]
    num: i32,
}

type Pool = Option<zenoh::shm::ShmProvider<zenoh::shm::PosixShmProviderBackend>>;

/// The shared-memory pool of a baseline side (64 MiB), or `None` for the network path.
fn pool(shm: bool) -> Pool {
    if !shm {
        return None;
    }
    zenoh::shm::ShmProviderBuilder::default_backend(64 << 20)
        .wait()
        .ok()
}

/// A shared-memory buffer of `len` bytes, when there is a pool with room (allocated as the
/// plugin allocates).
fn shm_buffer(pool: &Pool, len: usize) -> Option<zenoh::shm::ZShmMut> {
    aimrt_zenoh::shm_alloc(pool.as_ref()?, len).ok()
}

/// `bytes` as a payload: copied into a shared-memory buffer of its size when there is a
/// pool (as the plugin does), else as is.
fn payload(pool: &Pool, bytes: &[u8]) -> zenoh::bytes::ZBytes {
    if let Some(mut buf) = shm_buffer(pool, bytes.len()) {
        buf[..bytes.len()].copy_from_slice(bytes);
        return buf.into();
    }
    bytes.to_vec().into()
}

/// `header` then `msg` encoded behind it, written once: into a shared-memory buffer when
/// there is a pool with room, else into a new buffer.
fn typed_payload(pool: &Pool, header: &[u8], msg: &ExampleEventMsg) -> zenoh::bytes::ZBytes {
    use prost::Message as _;
    let len = header.len() + msg.encoded_len();
    if let Some(mut buf) = shm_buffer(pool, len) {
        buf[..header.len()].copy_from_slice(header);
        let mut rest = &mut buf[header.len()..len];
        if msg.encode(&mut rest).is_ok() {
            return buf.into();
        }
    }
    let mut out = Vec::with_capacity(len);
    out.extend_from_slice(header);
    // A `Vec` grows as needed: encoding into it cannot fail.
    let _ = msg.encode(&mut out);
    out.into()
}

/// The typed pong's answer to one received payload: its message decoded, then encoded
/// again behind a header with the same serialization type and meta. `None`: not AimRT's
/// layout or not the message.
fn typed_echo(pool: &Pool, bytes: &[u8]) -> Option<zenoh::bytes::ZBytes> {
    use prost::Message as _;
    let view = aimrt_zenoh::wire::decode_channel(bytes).ok()?;
    let msg = ExampleEventMsg::decode(view.message).ok()?;
    let header = aimrt_zenoh::wire::channel_header(
        view.serialization_type,
        view.meta.iter(),
        msg.encoded_len(),
    )
    .ok()?;
    Some(typed_payload(pool, &header, &msg))
}

/// The typed ping's decode of an echo: `true` when it holds the message.
fn typed_receive(bytes: &[u8]) -> bool {
    use prost::Message as _;
    aimrt_zenoh::wire::decode_channel(bytes)
        .ok()
        .and_then(|view| ExampleEventMsg::decode(view.message).ok())
        .is_some_and(|m| m.num == 1)
}

fn pong(cfg: &str, ping_key: &str, pong_key: &str, shm: bool, mode: Mode) -> i32 {
    let Some(session) = open(cfg) else { return 1 };
    let publisher = match session.declare_publisher(pong_key.to_owned()).wait() {
        Ok(p) => p,
        Err(e) => {
            eprintln!("cannot declare {pong_key}: {e}");
            return 1;
        }
    };
    let pool = pool(shm);
    let numbered = Numbered::new(mode);
    let subscriber = session
        .declare_subscriber(ping_key.to_owned())
        .callback(move |sample| {
            let bytes = sample.payload().to_bytes();
            let answer = match mode {
                Mode::Bytes => Some(payload(&pool, &bytes)),
                Mode::Typed => typed_echo(&pool, &bytes),
            };
            if let Some(answer) = answer {
                let _ = numbered.put(&publisher, answer);
            }
        })
        .wait();
    if let Err(e) = subscriber {
        eprintln!("cannot subscribe to {ping_key}: {e}");
        return 1;
    }
    println!("ready");
    loop {
        std::thread::sleep(Duration::from_secs(3600));
    }
}

/// The meta the runtime sends with a channel message.
const BENCH_META: [(&str, &str); 3] = [
    ("aimrt-serialization_type", "pb"),
    ("aimrt-pub_seq", "1"),
    ("aimrt-pub_ts", "1795386628205071149"),
];

/// The bench's message: `msg` of `size` bytes.
fn bench_message(size: usize) -> ExampleEventMsg {
    ExampleEventMsg {
        msg: "x".repeat(size),
        num: 1,
    }
}

/// AimRT's channel payload of the bench's message of `size` bytes, with the meta the
/// runtime sends.
fn bench_payload(size: usize) -> Vec<u8> {
    use prost::Message as _;
    let message = bench_message(size).encode_to_vec();
    aimrt_zenoh::wire::encode_channel("pb", BENCH_META, &message).expect("a payload under 4 GiB")
}

fn ping(
    cfg: &str,
    (ping_key, pong_key): (&str, &str),
    size: usize,
    n: u64,
    samples: usize,
    shm: bool,
    mode: Mode,
) -> i32 {
    use prost::Message as _;
    use std::sync::{Arc, Condvar, Mutex};
    let (send_spin, recv_spin) = match (
        spin_of("AIMRT_PROBE_SEND_SPIN_NS"),
        spin_of("AIMRT_PROBE_RECV_SPIN_NS"),
    ) {
        (Ok(send), Ok(recv)) => (send, recv),
        (Err(e), _) | (_, Err(e)) => {
            eprintln!("{e}");
            return 1;
        }
    };
    let Some(session) = open(cfg) else { return 1 };
    let Ok(publisher) = session.declare_publisher(ping_key.to_owned()).wait() else {
        return 1;
    };
    // Echoes, waited for without spinning (as the benchmark's side of ours).
    let got = Arc::new((Mutex::new(0u64), Condvar::new()));
    let counted = got.clone();
    let Ok(_subscriber) = session
        .declare_subscriber(pong_key.to_owned())
        .callback(move |sample| {
            spin(recv_spin);
            if mode == Mode::Typed && !typed_receive(&sample.payload().to_bytes()) {
                return;
            }
            *counted.0.lock().unwrap_or_else(|e| e.into_inner()) += 1;
            counted.1.notify_all();
        })
        .wait()
    else {
        return 1;
    };
    let pool = pool(shm);
    let bytes = bench_payload(size);
    let message = bench_message(size);
    let Ok(header) = aimrt_zenoh::wire::channel_header("pb", BENCH_META, message.encoded_len())
    else {
        return 1;
    };
    let numbered = Numbered::new(mode);
    let send = || {
        let p = match mode {
            Mode::Bytes => payload(&pool, &bytes),
            Mode::Typed => typed_payload(&pool, &header, &message),
        };
        let _ = numbered.put(&publisher, p);
        spin(send_spin);
    };
    let now = || *got.0.lock().unwrap_or_else(|e| e.into_inner());
    // Waits until `target` echoes arrived (`false` after `patience`), counting a wait that
    // blocked for `STALL` or more in `stalls`; the clock is read only when it blocks.
    let stalls = std::cell::Cell::new(0u64);
    let wait = |target: u64, patience: Duration| {
        let guard = got.0.lock().unwrap_or_else(|e| e.into_inner());
        if *guard >= target {
            return true;
        }
        let blocked = Instant::now();
        let (guard, _) = got
            .1
            .wait_timeout_while(guard, patience, |n| *n < target)
            .unwrap_or_else(|e| e.into_inner());
        if blocked.elapsed() >= STALL {
            stalls.set(stalls.get() + 1);
        }
        *guard >= target
    };
    // The echo must be there: a message every 10 ms until one comes back.
    let ready = Instant::now() + Duration::from_secs(20);
    while now() == 0 {
        if Instant::now() > ready {
            eprintln!("no echo on {pong_key} within 20 s");
            return 2;
        }
        send();
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(100));
    // Marks around the throughput phase: the benchmark reads this process's threads then.
    println!("measuring");
    let base = now();
    let t0 = Instant::now();
    let window = window(size);
    for k in 0..n {
        if k >= window {
            wait(base + k + 1 - window, Duration::from_secs(2));
        }
        send();
    }
    wait(base + n, Duration::from_secs(10));
    let delivered = now() - base;
    let rate = delivered as f64 / t0.elapsed().as_secs_f64();
    // The latency phase's waits are not the throughput phase's stalls.
    let stalls = stalls.get();
    println!("measured");
    let mut lat = Vec::with_capacity(samples);
    for _ in 0..samples {
        let before = now();
        let t = Instant::now();
        send();
        if wait(before + 1, Duration::from_secs(2)) {
            lat.push(t.elapsed().as_secs_f64() * 1e6);
        }
    }
    lat.sort_by(f64::total_cmp);
    let pct = |p: f64| {
        lat.get(((lat.len() as f64 - 1.0) * p / 100.0).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    println!(
        "{{\"msgs_per_s\": {rate:.1}, \"delivered\": {delivered}, \"sent\": {n}, \"rtt_p50_us\": {:.1}, \"rtt_p99_us\": {:.1}, \"stalls\": {stalls}}}",
        pct(50.0),
        pct(99.0)
    );
    let _ = session.close().wait();
    0
}

/// The busy work the environment variable `name` asks for: none when unset, else its
/// nanoseconds; `Err` names a value that is not a count of nanoseconds.
fn spin_of(name: &str) -> Result<Duration, String> {
    match std::env::var(name) {
        Err(std::env::VarError::NotPresent) => Ok(Duration::ZERO),
        Ok(v) => v
            .parse()
            .map(Duration::from_nanos)
            .map_err(|_| format!("{name}: '{v}' is not a count of nanoseconds, e.g. 500")),
        Err(std::env::VarError::NotUnicode(v)) => Err(format!(
            "{name}: {v:?} is not a count of nanoseconds, e.g. 500"
        )),
    }
}

/// Busy work for `d`, as a slower side's own code would take.
fn spin(d: Duration) {
    if d.is_zero() {
        return;
    }
    let until = Instant::now() + d;
    while Instant::now() < until {
        std::hint::spin_loop();
    }
}

/// A window wait this long or longer is a stall (reported as `stalls`). For small
/// messages, whose round trip takes about 0.1 ms, it is most likely zenoh's transmit task
/// backing off while a batch is being written, until `batching.time_limit` (1 ms) has
/// passed, on tokio's 1 ms timer; for large ones it is as likely their own time. The
/// benchmark's side of ours counts the same (benches/src/zenoh.rs).
const STALL: Duration = Duration::from_micros(900);

/// Messages of `size` bytes a ping side keeps unanswered at most: 64, and no more than
/// 8 MiB (8 at 1 MiB). More only measures zenoh's `Drop` congestion control, which drops
/// what its queue cannot take: a lost message stalls the window for its 2 s patience.
fn window(size: usize) -> u64 {
    ((8usize << 20) / size.max(1)).clamp(1, 64) as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_probes_message_is_the_runtimes_byte_for_byte() {
        use prost::Message as _;
        let ours = aimrt_protocols::example::ExampleEventMsg {
            msg: "x".repeat(300),
            num: 1,
        };
        assert_eq!(bench_message(300).encode_to_vec(), ours.encode_to_vec());
        assert_eq!(event_pb("garbage", 7), {
            let m = aimrt_protocols::example::ExampleEventMsg {
                msg: "garbage".into(),
                num: 7,
            };
            m.encode_to_vec()
        });
    }

    #[test]
    fn the_typed_pong_echoes_a_payload_and_refuses_garbage() {
        let echo = typed_echo(&None, &bench_payload(64)).expect("an echo");
        assert_eq!(echo.to_bytes().as_ref(), bench_payload(64).as_slice());
        assert!(typed_receive(&bench_payload(64)));
        assert!(typed_echo(&None, b"\x01\x00").is_none());
        assert!(!typed_receive(b"garbage"));
    }

    /// The typed sides put what the plugin's publisher puts by default: zenoh's source
    /// info, numbered from 0; the bytes sides put plain samples.
    #[test]
    fn typed_puts_carry_a_sequence_number_and_bytes_puts_none() {
        let mut config = zenoh::Config::default();
        for (key, value) in [
            ("listen/endpoints", "[]"),
            ("scouting/multicast/enabled", "false"),
        ] {
            config.insert_json5(key, value).unwrap();
        }
        let session = zenoh::open(config).wait().unwrap();
        let heard = |mode: Mode| {
            let key = format!("probe/numbered/{mode:?}");
            let subscriber = session.declare_subscriber(&key).wait().unwrap();
            let publisher = session.declare_publisher(&key).wait().unwrap();
            let numbered = Numbered::new(mode);
            for _ in 0..3 {
                numbered.put(&publisher, bench_payload(64).into()).unwrap();
            }
            (0..3)
                .map(|_| {
                    let sample = subscriber.recv_timeout(Duration::from_secs(5));
                    let sample = sample.unwrap().expect("a sample within 5 s");
                    sample.source_info().map(|s| s.source_sn())
                })
                .collect::<Vec<_>>()
        };
        assert_eq!(heard(Mode::Typed), [Some(0), Some(1), Some(2)]);
        assert_eq!(heard(Mode::Bytes), [None, None, None]);
        session.close().wait().unwrap();
    }
}
