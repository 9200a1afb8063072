//! mqtt_plugin's payloads are AimRT's: the same fields AimRT's zenoh_plugin writes (both
//! lay them out with AimRT's `BufferOperator`), without zenoh's `u32` length prefix. Every
//! payload captured from AimRT's zenoh_plugin (`tests/fixtures/aimrt-wire/zenoh_*`), its
//! prefix taken off, is read by [`aimrt_wire::payload`] and written back byte for byte; and
//! a request and an answer as AimRT's mqtt_plugin lays them out, with its topics, are
//! ours byte for byte.

use aimrt_wire::payload::{put_channel_header, ChannelView, Request, Response};

const DIR: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../tests/fixtures/aimrt-wire"
);
const FUNC: &str = "pb:/aimrt.protocols.example.ExampleService/GetFooData";

fn fixture(file: &str) -> Vec<(String, Vec<u8>)> {
    let text = std::fs::read_to_string(format!("{DIR}/{file}")).unwrap();
    aimrt_plugin_api::__private::hex_lines(&text)
}

/// The bytes a zenoh length prefix covers.
fn unprefixed(label: &str, bytes: &[u8]) -> Vec<u8> {
    let said = u32::from_le_bytes(bytes[..4].try_into().unwrap()) as usize;
    assert_eq!(said, bytes.len() - 4, "{label}: a prefixed payload");
    bytes[4..].to_vec()
}

#[test]
fn aimrts_captured_payloads_without_the_prefix_read_and_write_back_the_same() {
    let mut read = 0;
    for (label, bytes) in fixture("zenoh_channel_pb.hex")
        .into_iter()
        .chain(fixture("zenoh_channel_to_sub.hex"))
        // The one with junk after its prefixed length tests zenoh's prefix, not the fields.
        .filter(|(l, _)| l != "key_expr" && l != "trailing_junk")
    {
        let body = unprefixed(&label, &bytes);
        let v = ChannelView::read(&body).unwrap_or_else(|e| panic!("{label}: {e}"));
        let mut again = Vec::new();
        put_channel_header(&mut again, v.serialization_type, v.meta.iter()).unwrap();
        again.extend_from_slice(v.message);
        assert_eq!(again, body, "{label}");
        read += 1;
    }
    for (label, bytes) in fixture("zenoh_rpc_req.hex")
        .into_iter()
        .chain(fixture("zenoh_rpc_server_rsp.hex"))
    {
        let written = if (label.starts_with("request_") || label.starts_with("req_"))
            && !label.ends_with("key_expr")
        {
            let r = Request::read(&unprefixed(&label, &bytes)).unwrap();
            let format = if label.ends_with("json") {
                "json"
            } else {
                "pb"
            };
            assert_eq!(r.serialization_type, format, "{label}");
            let mut out = Vec::new();
            r.write_to(&mut out).unwrap();
            out
        } else if label == "python_reply_1" || label.starts_with("rsp_") {
            let r = Response::read(&unprefixed(&label, &bytes)).unwrap();
            assert_eq!(r.status, 0, "{label}");
            let mut out = Vec::new();
            r.write_to(&mut out).unwrap();
            out
        } else {
            continue;
        };
        assert_eq!(written, bytes[4..], "{label}");
        read += 1;
    }
    assert!(read >= 14, "{read} payloads read");
}

fn hex(s: &str) -> Vec<u8> {
    let s: String = s.split_whitespace().collect();
    (0..s.len() / 2)
        .map(|i| u8::from_str_radix(&s[2 * i..2 * i + 2], 16).unwrap())
        .collect()
}

#[test]
fn a_request_and_its_answer_are_aimrts_mqtt_layout_byte_for_byte() {
    // Client "cli", request id 0, meta {k: v}, GetFooDataReq{msg: "hi"}.
    let reply_to = aimrt_mqtt::wire::response_topic("cli", FUNC);
    assert_eq!(
        reply_to,
        "aimrt_rpc_rsp/cli/%2Faimrt.protocols.example.ExampleService%2FGetFooData"
    );
    let request = Request {
        serialization_type: "pb".into(),
        reply_to,
        req_id: 0u32.to_le_bytes(),
        meta: vec![("k".into(), "v".into())],
        body: vec![0x0a, 0x02, 0x68, 0x69],
    };
    // str8 "pb", str8 topic (72 bytes), u32_le 0, u8 1 pair, str16 "k", str16 "v", body.
    let golden = hex(
        "02 70 62 48 61 69 6d 72 74 5f 72 70 63 5f 72 73 70 2f 63 6c 69 2f 25 32 46 61 69 6d 72 74 2e 70
         72 6f 74 6f 63 6f 6c 73 2e 65 78 61 6d 70 6c 65 2e 45 78 61 6d 70 6c 65 53 65 72 76 69 63 65 25
         32 46 47 65 74 46 6f 6f 44 61 74 61 00 00 00 00 01 01 00 6b 01 00 76 0a 02 68 69",
    );
    let mut ours = Vec::new();
    request.write_to(&mut ours).unwrap();
    assert_eq!(ours, golden);
    assert_eq!(Request::read(&golden).unwrap(), request);

    // The answer: str8 "pb", the id bytes, u32_le status, body; an error answer is the
    // same without a body.
    let ok = Response {
        serialization_type: "pb".into(),
        req_id: [0; 4],
        status: 0,
        body: vec![0x0a, 0x02, 0x68, 0x69],
    };
    let golden = hex("02 70 62 00 00 00 00 00 00 00 00 0a 02 68 69");
    let mut ours = Vec::new();
    ok.write_to(&mut ours).unwrap();
    assert_eq!(ours, golden);
    assert_eq!(Response::read(&golden).unwrap(), ok);
    let failed = Response::read(&hex("02 70 62 00 00 00 00 eb 03 00 00")).unwrap();
    assert_eq!(failed.status, 1003);
    assert!(failed.body.is_empty());
}

#[test]
fn every_cut_and_garbage_is_an_error_or_reads_back_the_same_never_a_panic() {
    let request = Request {
        serialization_type: "pb".into(),
        reply_to: aimrt_mqtt::wire::response_topic("cli", FUNC),
        req_id: [1, 2, 3, 4],
        meta: vec![("key".into(), "value".into())],
        body: b"body".to_vec(),
    };
    let mut bytes = Vec::new();
    request.write_to(&mut bytes).unwrap();
    let fields = bytes.len() - request.body.len();
    for cut in 0..bytes.len() {
        let r = Request::read(&bytes[..cut]);
        assert_eq!(r.is_ok(), cut >= fields, "cut {cut}");
        aimrt_mqtt::wire::read_any(&bytes[..cut]);
    }
    // Deterministic garbage of every length up to 300: read every way, never a panic.
    let mut x = 0x2545_f491_u32;
    for len in 0..300 {
        let bytes: Vec<u8> = (0..len)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                x as u8
            })
            .collect();
        aimrt_mqtt::wire::read_any(&bytes);
    }
}
