//! Golden tests over every capture in `tests/fixtures/aimrt-wire/` (bytes AimRT's own
//! net_plugin and zenoh_plugin sent and accepted): the message inside each frame, sample,
//! datagram or HTTP body is exactly the bytes our prost types encode, and decodes back.
//!
//! This checks the message layer only. The framing around it (TCP's `YT` header, the
//! str8/str16 meta of TCP, UDP and zenoh, the HTTP headers) is the transports' part:
//! issues 18 (zenoh) and 19 (net_plugin channels) turn these same fixtures into tests of
//! their encoders and decoders.

use std::collections::HashMap;

use aimrt_plugin_api::channel::Message;
use aimrt_protocols::example::{ExampleEventMsg, GetFooDataReq, GetFooDataRsp};

/// The `<label> <hex>` lines of one fixture file, by label.
fn fixture(file: &str) -> HashMap<String, Vec<u8>> {
    let path = format!(
        "{}/../tests/fixtures/aimrt-wire/{file}",
        env!("CARGO_MANIFEST_DIR")
    );
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    aimrt_plugin_api::__private::hex_lines(&text)
        .into_iter()
        .collect()
}

fn event(msg: &str, num: i32) -> ExampleEventMsg {
    ExampleEventMsg {
        msg: msg.to_owned(),
        num,
    }
}

/// `bytes` ends with the `pb` encoding of `message`, and those bytes decode to it.
fn ends_with_pb<M: Message + PartialEq + std::fmt::Debug>(
    file: &str,
    label: &str,
    bytes: &[u8],
    message: &M,
) {
    let ours = message.encode("pb").expect("encode");
    assert!(
        bytes.ends_with(&ours),
        "{file} {label}: AimRT's bytes do not end with our encoding of {message:?}"
    );
    let tail = &bytes[bytes.len() - ours.len()..];
    assert_eq!(
        &M::decode("pb", tail).expect("decode"),
        message,
        "{file} {label}"
    );
}

#[test]
fn channel_messages_in_every_transport_capture_are_ours() {
    let cases: &[(&str, &[(&str, ExampleEventMsg)])] = &[
        (
            "tcp_channel_pb.hex",
            &[
                ("frame_1", event("count: 1", 1)),
                ("frame_2", event("count: 2", 2)),
            ],
        ),
        (
            "tcp_channel_to_sub.hex",
            &[
                ("replay_of_frame_1", event("count: 1", 1)),
                ("min_pb", event("from python tcp min", 50)),
            ],
        ),
        (
            "udp_channel_pb.hex",
            &[
                ("datagram_1", event("count: 1", 1)),
                ("datagram_2", event("count: 2", 2)),
            ],
        ),
        (
            "udp_channel_to_sub.hex",
            &[
                ("replay_of_datagram_1", event("count: 1", 1)),
                ("min_pb", event("from python udp min", 60)),
            ],
        ),
        (
            "zenoh_channel_pb.hex",
            &[
                ("sample_1", event("count: 1", 1)),
                ("sample_2", event("count: 2", 2)),
            ],
        ),
        (
            "zenoh_channel_to_sub.hex",
            &[
                ("replay_of_sample_1", event("count: 1", 1)),
                ("min_pb", event("from python min", 42)),
                ("custom_meta_pb", event("from python meta", 43)),
            ],
        ),
        (
            "http_channel_pb.txt",
            &[
                ("request_1", event("count: 1", 1)),
                ("body_1", event("count: 1", 1)),
            ],
        ),
        (
            "http_channel_to_sub.txt",
            &[
                ("sent_replay_of_request_1", event("count: 1", 1)),
                ("sent_min_pb_no_host", event("from python http min", 46)),
            ],
        ),
    ];
    for (file, frames) in cases {
        let f = fixture(file);
        for (label, message) in frames.iter() {
            let bytes = f
                .get(*label)
                .unwrap_or_else(|| panic!("{file} has no line '{label}'"));
            ends_with_pb(file, label, bytes, message);
        }
    }
}

#[test]
fn rpc_requests_and_responses_in_every_capture_are_ours() {
    let req = |msg: &str| GetFooDataReq {
        msg: msg.to_owned(),
    };
    let rsp = |msg: &str| GetFooDataRsp {
        code: 0,
        msg: msg.to_owned(),
        data: None,
    };
    let http = fixture("http_rpc_req.txt");
    for label in ["request_1", "request_2"] {
        let n = &label[label.len() - 1..];
        ends_with_pb(
            "http_rpc_req.txt",
            label,
            &http[label],
            &req(&format!("hello world foo, count {n}")),
        );
    }
    let zenoh = fixture("zenoh_rpc_req.hex");
    for label in ["request_1", "request_2"] {
        let n = &label[label.len() - 1..];
        ends_with_pb(
            "zenoh_rpc_req.hex",
            label,
            &zenoh[label],
            &req(&format!("hello world foo, count {n}")),
        );
    }
    let server = fixture("zenoh_rpc_server_rsp.hex");
    ends_with_pb(
        "zenoh_rpc_server_rsp.hex",
        "req_replay_of_request_1",
        &server["req_replay_of_request_1"],
        &req("hello world foo, count 1"),
    );
    ends_with_pb(
        "zenoh_rpc_server_rsp.hex",
        "rsp_replay_of_request_1",
        &server["rsp_replay_of_request_1"],
        &rsp("echo hello world foo, count 1"),
    );
    // The JSON reply is the proto3 mapping as AimRT prints it, byte for byte.
    let json = rsp("echo python json req").encode("json").expect("json");
    assert!(
        server["rsp_json"].ends_with(&json),
        "zenoh rsp_json does not end with {}",
        String::from_utf8_lossy(&json)
    );
}
