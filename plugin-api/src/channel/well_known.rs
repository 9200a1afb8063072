//! Google's well-known types (`google.protobuf.Timestamp`, `Empty`, the wrappers, …) as
//! [`Message`](super::Message)s, from the `pbjson-types` crate (re-exported as
//! [`crate::pbjson_types`]): their JSON is the proto3 mapping (a `Timestamp` is an RFC 3339
//! string, a `Duration` `"1.5s"`, a wrapper its bare value), as AimRT's protobuf prints it.
//!
//! Code from `aimrt-codegen` takes every `google.protobuf` type from here, so a `.proto`
//! file that imports `google/protobuf/timestamp.proto` needs nothing more, and a service
//! method may take or return one (`rpc Reset(google.protobuf.Empty) returns (…)`). Their
//! schema in recordings is the descriptor set of these files (`google_protobuf.fds.bin`,
//! checked against protox's by a test of aimrt-codegen).

use pbjson_types as wkt;

/// The serialized `FileDescriptorSet` of the files below.
static SET: &[u8] = include_bytes!("google_protobuf.fds.bin");

macro_rules! well_known {
    ($($ty:ident => $name:literal),* $(,)?) => {
        $(crate::prost_message!(wkt::$ty, $name, SET);)*
    };
}

well_known!(
    Any => "google.protobuf.Any",
    Duration => "google.protobuf.Duration",
    Empty => "google.protobuf.Empty",
    FieldMask => "google.protobuf.FieldMask",
    Struct => "google.protobuf.Struct",
    Value => "google.protobuf.Value",
    ListValue => "google.protobuf.ListValue",
    Timestamp => "google.protobuf.Timestamp",
    BoolValue => "google.protobuf.BoolValue",
    BytesValue => "google.protobuf.BytesValue",
    DoubleValue => "google.protobuf.DoubleValue",
    FloatValue => "google.protobuf.FloatValue",
    Int32Value => "google.protobuf.Int32Value",
    Int64Value => "google.protobuf.Int64Value",
    StringValue => "google.protobuf.StringValue",
    UInt32Value => "google.protobuf.UInt32Value",
    UInt64Value => "google.protobuf.UInt64Value",
);

#[cfg(test)]
mod tests {
    use super::wkt;
    use crate::channel::Message;

    #[test]
    fn timestamps_and_wrappers_travel_in_pb_and_in_the_proto3_json_mapping() {
        assert_eq!(wkt::Timestamp::type_name(), "pb:google.protobuf.Timestamp");
        let t = wkt::Timestamp {
            seconds: 1_700_000_000,
            nanos: 500_000_000,
        };
        // As AimRT's protobuf: UTC as `Z`, and 0, 3, 6 or 9 digits of fraction.
        for (seconds, nanos, json) in [
            (1_700_000_000, 500_000_000, r#""2023-11-14T22:13:20.500Z""#),
            (1, 0, r#""1970-01-01T00:00:01Z""#),
            (1, 1_000, r#""1970-01-01T00:00:01.000001Z""#),
        ] {
            let stamp = wkt::Timestamp { seconds, nanos };
            assert_eq!(stamp.encode("json").expect("json"), json.as_bytes());
        }
        // The 64-bit wrappers are strings, as protobuf's JSON has them.
        let long = wkt::Int64Value { value: -5 };
        assert_eq!(long.encode("json").expect("json"), br#""-5""#);
        let ulong = wkt::UInt64Value { value: u64::MAX };
        assert_eq!(
            ulong.encode("json").expect("json"),
            br#""18446744073709551615""#
        );
        let pb = t.encode("pb").expect("pb");
        assert_eq!(wkt::Timestamp::decode("pb", &pb).expect("pb back"), t);
        assert_eq!(
            wkt::Timestamp::decode("json", br#""2023-11-14T22:13:20.5Z""#).expect("json back"),
            t
        );
        let d = wkt::Duration {
            seconds: 1,
            nanos: 500_000_000,
        };
        assert_eq!(d.encode("json").expect("json"), br#""1.500s""#);
        let s = wkt::StringValue { value: "hi".into() };
        assert_eq!(s.encode("json").expect("json"), br#""hi""#);
        assert_eq!(wkt::Empty {}.encode("json").expect("json"), b"{}");
        assert_eq!(wkt::Empty::type_name(), "pb:google.protobuf.Empty");
    }

    #[test]
    fn their_schema_is_the_set_of_googles_files() {
        use prost::Message as _;
        let schema = wkt::Timestamp::schema();
        assert_eq!(
            (schema.encoding, schema.name),
            ("protobuf", "google.protobuf.Timestamp")
        );
        let set = pbjson_types::FileDescriptorSet::decode(schema.data).expect("a set");
        let names: Vec<&str> = set.file.iter().map(|f| f.name()).collect();
        for file in [
            "google/protobuf/timestamp.proto",
            "google/protobuf/wrappers.proto",
        ] {
            assert!(names.contains(&file), "{file} is not in {names:?}");
        }
    }
}
