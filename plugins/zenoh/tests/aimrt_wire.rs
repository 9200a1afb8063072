//! Every capture of AimRT's own zenoh_plugin in `tests/fixtures/aimrt-wire/zenoh_*` is a
//! decode test: the same message, the same serialization type, and the meta compared as a
//! set (AimRT writes it in hash order). Each labelled line of each `zenoh_*` file must have
//! a case here: a new capture without one fails the test.

use std::collections::BTreeSet;

use aimrt_plugin_api::channel::Message;
use aimrt_protocols::example::{ExampleEventMsg, GetFooDataReq, GetFooDataRsp};
use aimrt_zenoh::wire::{
    channel_key, decode_request, decode_response, encode_request, encode_response, read_any,
    rpc_pattern, ChannelPayload,
};

const DIR: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../tests/fixtures/aimrt-wire"
);
const EVENT: &str = "pb:aimrt.protocols.example.ExampleEventMsg";
const FUNC: &str = "pb:/aimrt.protocols.example.ExampleService/GetFooData";

fn meta_set(meta: &[(String, String)]) -> BTreeSet<(&str, &str)> {
    meta.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect()
}

fn event(msg: &str, num: i32) -> ExampleEventMsg {
    ExampleEventMsg {
        msg: msg.to_owned(),
        num,
    }
}

fn text(bytes: &[u8]) -> &str {
    std::str::from_utf8(bytes).expect("a key expression is text")
}

/// A channel payload: its type, its meta as a set, its message; our encoding of what we
/// read (meta in the order read) is AimRT's bytes up to the prefixed length.
fn channel(label: &str, bytes: &[u8], format: &str, meta: &[(&str, &str)], msg: ExampleEventMsg) {
    let p = ChannelPayload::decode(bytes).unwrap_or_else(|e| panic!("{label}: {e}"));
    assert_eq!(p.serialization_type, format, "{label}");
    let want: BTreeSet<(&str, &str)> = meta.iter().copied().collect();
    assert_eq!(meta_set(&p.meta), want, "{label}");
    assert_eq!(
        ExampleEventMsg::decode(format, &p.message).unwrap(),
        msg,
        "{label}"
    );
    let ours = p.encode().unwrap();
    assert_eq!(ours[..], bytes[..ours.len()], "{label}");
}

fn request(label: &str, bytes: &[u8], format: &str, id: [u8; 4], meta_keys: &[&str], msg: &str) {
    let r = decode_request(bytes).unwrap_or_else(|e| panic!("{label}: {e}"));
    assert_eq!(r.serialization_type, format, "{label}");
    assert_eq!(r.reply_to, rpc_pattern(FUNC, ""), "{label}");
    assert_eq!(r.req_id, id, "{label}");
    let keys: BTreeSet<&str> = r.meta.iter().map(|(k, _)| k.as_str()).collect();
    assert_eq!(keys, meta_keys.iter().copied().collect(), "{label}");
    let req = GetFooDataReq::decode(format, &r.body).unwrap();
    assert_eq!(req.msg, msg, "{label}");
    assert_eq!(encode_request(&r).unwrap(), bytes, "{label}");
}

fn response(label: &str, bytes: &[u8], format: &str, id: [u8; 4], status: u32, msg: &str) {
    let r = decode_response(bytes).unwrap_or_else(|e| panic!("{label}: {e}"));
    assert_eq!(r.serialization_type, format, "{label}");
    assert_eq!(r.req_id, id, "{label}");
    assert_eq!(r.status, status, "{label}");
    if status == 0 {
        let rsp = GetFooDataRsp::decode(format, &r.body).unwrap();
        assert_eq!(rsp.msg, msg, "{label}");
    } else {
        assert!(r.body.is_empty(), "{label}");
    }
    assert_eq!(encode_response(&r).unwrap(), bytes, "{label}");
}

const AIMRT_REQUEST_KEYS: &[&str] = &[
    "aimrt-serialization_type",
    "aimrt-backend",
    "aimrt-request_id",
    "aimrt-function_name",
];

fn case(file: &str, label: &str, bytes: &[u8]) {
    let pub_meta = |seq: &str, ts: &str| -> Vec<(String, String)> {
        vec![
            ("aimrt-pub_ts".into(), ts.into()),
            ("aimrt-pub_seq".into(), seq.into()),
            ("aimrt-serialization_type".into(), "pb".into()),
        ]
    };
    match (file, label) {
        ("zenoh_channel_pb.hex", "key_expr") => {
            assert_eq!(text(bytes), channel_key("test_topic", EVENT, ""))
        }
        ("zenoh_channel_pb.hex", "sample_1" | "sample_2")
        | ("zenoh_channel_to_sub.hex", "replay_of_sample_1") => {
            let n = if label == "sample_2" { 2 } else { 1 };
            let p = ChannelPayload::decode(bytes).unwrap();
            let ts = p
                .meta
                .iter()
                .find(|(k, _)| k == "aimrt-pub_ts")
                .map(|(_, v)| v.clone())
                .expect("aimrt-pub_ts");
            assert!(ts.parse::<u64>().is_ok(), "{label}: pub_ts {ts}");
            let meta = pub_meta(&n.to_string(), &ts);
            let meta: Vec<(&str, &str)> =
                meta.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect();
            channel(label, bytes, "pb", &meta, event(&format!("count: {n}"), n));
        }
        ("zenoh_channel_to_sub.hex", "min_pb") => {
            channel(label, bytes, "pb", &[], event("from python min", 42))
        }
        ("zenoh_channel_to_sub.hex", "custom_meta_pb") => channel(
            label,
            bytes,
            "pb",
            &[("my-key", "my-val")],
            event("from python meta", 43),
        ),
        ("zenoh_channel_to_sub.hex", "json") => {
            channel(label, bytes, "json", &[], event("from python json", 44))
        }
        ("zenoh_channel_to_sub.hex", "trailing_junk") => {
            // Four bytes beyond the prefixed length: ignored, as AimRT does.
            channel(label, bytes, "pb", &[], event("from python trailing", 45));
            assert_eq!(bytes.len(), 4 + 28 + 4);
        }
        ("zenoh_rpc_req.hex", "request_key_expr") => {
            assert_eq!(text(bytes), format!("req/{}", rpc_pattern(FUNC, "")))
        }
        ("zenoh_rpc_req.hex", "response_key_expr") => {
            assert_eq!(text(bytes), format!("rsp/{}", rpc_pattern(FUNC, "")))
        }
        ("zenoh_rpc_req.hex", "request_1")
        | ("zenoh_rpc_server_rsp.hex", "req_replay_of_request_1") => request(
            label,
            bytes,
            "pb",
            [0; 4],
            AIMRT_REQUEST_KEYS,
            "hello world foo, count 1",
        ),
        ("zenoh_rpc_req.hex", "request_2") => request(
            label,
            bytes,
            "pb",
            [1, 0, 0, 0],
            AIMRT_REQUEST_KEYS,
            "hello world foo, count 2",
        ),
        ("zenoh_rpc_req.hex", "python_reply_1") => response(
            label,
            bytes,
            "pb",
            [0; 4],
            0,
            "python echo hello world foo, count 1",
        ),
        ("zenoh_rpc_req.hex", "python_error_reply") => {
            response(label, bytes, "pb", [0; 4], 1008, "")
        }
        ("zenoh_rpc_server_rsp.hex", "rsp_replay_of_request_1") => response(
            label,
            bytes,
            "pb",
            [0; 4],
            0,
            "echo hello world foo, count 1",
        ),
        ("zenoh_rpc_server_rsp.hex", "req_min_pb_req_id_12345678") => request(
            label,
            bytes,
            "pb",
            [0x78, 0x56, 0x34, 0x12],
            &[],
            "python min req",
        ),
        ("zenoh_rpc_server_rsp.hex", "rsp_min_pb_req_id_12345678") => response(
            label,
            bytes,
            "pb",
            [0x78, 0x56, 0x34, 0x12],
            0,
            "echo python min req",
        ),
        ("zenoh_rpc_server_rsp.hex", "req_json") => request(
            label,
            bytes,
            "json",
            [0x22, 0, 0, 0],
            &[],
            "python json req",
        ),
        ("zenoh_rpc_server_rsp.hex", "rsp_json") => response(
            label,
            bytes,
            "json",
            [0x22, 0, 0, 0],
            0,
            "echo python json req",
        ),
        ("zenoh_rpc_server_rsp.hex", "req_bad_pb") => {
            // The layout is fine; the body is not a GetFooDataReq (AimRT's server sent no
            // answer; ours answers 1007 from the runtime's decoder).
            let r = decode_request(bytes).unwrap();
            assert_eq!(r.body, [0xff, 0xff, 0xff]);
            assert!(GetFooDataReq::decode("pb", &r.body).is_err());
        }
        _ => panic!("{file}: no test case for the capture '{label}'; add one"),
    }
}

#[test]
fn every_zenoh_capture_decodes_as_aimrt_sent_it() {
    let mut files: Vec<String> = std::fs::read_dir(DIR)
        .expect("the fixtures directory")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("zenoh_"))
        .collect();
    files.sort();
    assert_eq!(files.len(), 4, "{files:?}");
    let mut cases = 0;
    for file in &files {
        let text = std::fs::read_to_string(format!("{DIR}/{file}")).unwrap();
        for (label, bytes) in aimrt_plugin_api::__private::hex_lines(&text) {
            case(file, &label, &bytes);
            cases += 1;
        }
    }
    assert_eq!(cases, 21);
}

/// Every capture damaged every way (`__private::damaged`): an error or a payload, never a
/// panic; a channel payload that reads encodes again to bytes that read the same. The
/// fuzz target `zenoh_wire` does the same with any bytes, outside CI.
#[test]
fn every_zenoh_capture_damaged_anywhere_is_an_error_or_reads_back() {
    let files = [
        "zenoh_channel_pb.hex",
        "zenoh_channel_to_sub.hex",
        "zenoh_rpc_req.hex",
        "zenoh_rpc_server_rsp.hex",
    ];
    let tried = aimrt_plugin_api::__private::read_damaged_captures(DIR, &files, read_any);
    assert!(tried > 10_000, "{tried} damaged captures");
}

#[test]
fn aimrts_own_native_config_loads_unchanged() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../tests/aimrt-configs/zenoh_native_config.json5"
    );
    let text = std::fs::read_to_string(path).expect("AimRT's zenoh_native_config.json5");
    assert!(text.contains("224.0.0.224:7446"), "{path}");
    // Loaded as the plugin loads native_cfg_path; no session is opened (its multicast
    // scouting would reach beyond this test).
    let config = aimrt_zenoh::load_native_config(path).expect("it loads");
    let mode = config.get_json("mode").expect("a mode");
    assert_eq!(mode, "\"peer\"");
    let ours = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/zenoh_native_a.json5"
    );
    assert!(aimrt_zenoh::load_native_config(ours).is_ok());
    assert!(aimrt_zenoh::load_native_config("/no/such.json5")
        .unwrap_err()
        .contains("is not a file"));
}
