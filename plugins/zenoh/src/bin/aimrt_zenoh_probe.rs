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
//!                                                      print "sample <bytes> shm=<bool>" for
//!                                                      each of n samples (60 s at most)
//! ```
//! It exits 0 when done, 1 on a usage or session error, 2 when `listen` timed out.

use std::time::{Duration, Instant};

use aimrt_zenoh::wire::{ChannelPayload, Request, Response};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let code = match args.iter().map(String::as_str).collect::<Vec<_>>()[..] {
        ["inject", cfg, key] => inject(cfg, key),
        ["call", cfg, domain, hex] => call(cfg, domain, hex),
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
        "usage: aimrt_zenoh_probe inject <native_cfg.json5> <key>\n       aimrt_zenoh_probe call <native_cfg.json5> <limit_domain> <request hex>\n       aimrt_zenoh_probe listen <native_cfg.json5> <key> <n>"
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

/// `ExampleEventMsg { msg, num }` in protobuf (num < 128).
fn event_pb(msg: &str, num: u8) -> Vec<u8> {
    let mut out = vec![0x0a, msg.len() as u8];
    out.extend_from_slice(msg.as_bytes());
    out.extend_from_slice(&[0x10, num]);
    out
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
        meta: vec![("probe".into(), "after-garbage".into())],
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
                println!("sample {} shm={shm}", sample.payload().len());
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

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn call(cfg: &str, domain: &str, request_hex: &str) -> i32 {
    let bytes: Option<Vec<u8>> = (0..request_hex.len() / 2)
        .map(|i| u8::from_str_radix(request_hex.get(2 * i..2 * i + 2)?, 16).ok())
        .collect();
    let mut request = match bytes.as_deref().map(Request::decode) {
        Some(Ok(r)) => r,
        _ => {
            eprintln!("the request is not hex of AimRT's request layout");
            return 1;
        }
    };
    if !domain.is_empty() {
        request.pattern = format!("{}/{domain}", request.pattern);
    }
    let Some(session) = open(cfg) else { return 1 };
    let answers = match session
        .declare_subscriber(format!("rsp/{}", request.pattern))
        .wait()
    {
        Ok(s) => s,
        Err(e) => {
            eprintln!("cannot subscribe to the answers: {e}");
            return 1;
        }
    };
    let payload = request.encode().expect("a request that decoded encodes");
    if let Err(e) = session
        .put(format!("req/{}", request.pattern), payload)
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
            Ok(Some(sample)) => match Response::decode(&sample.payload().to_bytes()) {
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
