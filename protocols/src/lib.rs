//! AimRT's example protobuf messages as Rust types, ready to publish: each implements
//! [`Message`](aimrt_plugin_api::channel::Message) with AimRT's type name
//! (`pb:aimrt.protocols.example.ExampleEventMsg`) and the formats `pb` and `json`, so a
//! Rust module and a C++ AimRT module agree on the name and the bytes.
//!
//! The types are generated at build time by prost from `proto/`, compiled by protox (a
//! protobuf compiler in Rust), so no `protoc` binary is needed.

/// `aimrt.protocols.example`.
#[allow(missing_docs, unreachable_pub)]
pub mod example {
    include!(concat!(env!("OUT_DIR"), "/aimrt.protocols.example.rs"));
}

aimrt_plugin_api::prost_message!(
    example::ExampleEventMsg,
    "aimrt.protocols.example.ExampleEventMsg"
);

#[cfg(test)]
mod tests {
    use super::example::ExampleEventMsg;
    use aimrt_plugin_api::channel::Message;

    #[test]
    fn both_formats_round_trip_with_aimrt_names() {
        assert_eq!(
            ExampleEventMsg::type_name(),
            "pb:aimrt.protocols.example.ExampleEventMsg"
        );
        assert_eq!(ExampleEventMsg::formats(), ["pb", "json"]);
        let m = ExampleEventMsg {
            msg: "count: 3".into(),
            num: 3,
        };
        let pb = m.encode("pb").unwrap();
        // Field 1 (string, tag 0x0a), field 2 (varint, tag 0x10): protobuf's wire format.
        assert_eq!(pb, b"\x0a\x08count: 3\x10\x03");
        assert_eq!(ExampleEventMsg::decode("pb", &pb).unwrap(), m);
        let json = m.encode("json").unwrap();
        assert_eq!(
            serde_json::from_slice::<serde_json::Value>(&json).unwrap(),
            serde_json::json!({"msg": "count: 3", "num": 3})
        );
        // Missing fields take their defaults, as protobuf's JSON mapping says.
        assert_eq!(
            ExampleEventMsg::decode("json", br#"{"num": 5}"#).unwrap(),
            ExampleEventMsg {
                msg: String::new(),
                num: 5
            }
        );
        assert!(ExampleEventMsg::decode("pb", b"\xff\xff").is_err());
    }
}
