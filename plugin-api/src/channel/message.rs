//! Message types: a name declared by the type, the formats it travels in, and how to
//! (de)serialize it.

use serde::de::DeserializeOwned;
use serde::Serialize;

/// Why a message could not be (de)serialized.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MessageError {
    /// The type does not support the format asked for.
    #[error("message type '{type_name}' does not support the format '{format}'; it supports {supported}")]
    UnsupportedFormat {
        /// The message type.
        type_name: String,
        /// The format asked for.
        format: String,
        /// The formats it supports, comma separated.
        supported: String,
    },
    /// Serializing failed.
    #[error("cannot serialize '{type_name}' as {format}: {message}")]
    Serialize {
        /// The message type.
        type_name: String,
        /// The format.
        format: String,
        /// The encoder's message.
        message: String,
    },
    /// Deserializing failed (malformed or foreign bytes).
    #[error("cannot deserialize '{type_name}' from {format}: {message}")]
    Deserialize {
        /// The message type.
        type_name: String,
        /// The format.
        format: String,
        /// The decoder's message.
        message: String,
    },
}

/// A message type of a channel (DESIGN §6).
///
/// The type name is declared by the type — never derived from `std::any::type_name` —
/// and is what publishers and subscribers in different libraries agree on, AimRT style:
/// `pb:aimrt.protocols.example.ExampleEventMsg` for protobuf, `serde:<name>` for serde
/// types. For a serde type, [`serde_message!`](crate::serde_message) writes the impl:
///
/// ```
/// #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
/// struct Hello { text: String, count: u32 }
/// aimrt_plugin_api::serde_message!(Hello, "example.Hello");
///
/// use aimrt_plugin_api::channel::Message;
/// assert_eq!(Hello::type_name(), "serde:example.Hello");
/// assert_eq!(Hello::formats(), ["postcard", "json"]);
/// let m = Hello { text: "hi".into(), count: 3 };
/// let json = m.encode("json").unwrap();
/// assert_eq!(json, br#"{"text":"hi","count":3}"#);
/// assert_eq!(Hello::decode("json", &json).unwrap(), m);
/// let bin = m.encode("postcard").unwrap();
/// assert_eq!(Hello::decode("postcard", &bin).unwrap(), m);
/// assert!(m.encode("pb").is_err());
/// ```
pub trait Message: Send + Sync + Sized + 'static {
    /// The type name every library agrees on.
    fn type_name() -> &'static str;
    /// The formats it travels in; the first is the default.
    fn formats() -> &'static [&'static str];
    /// Encodes the message in `format` (named `encode`, not `serialize`, so that it never
    /// clashes with serde's method on the same type).
    fn encode(&self, format: &str) -> Result<Vec<u8>, MessageError>;
    /// Decodes a message from `bytes` in `format`.
    fn decode(format: &str, bytes: &[u8]) -> Result<Self, MessageError>;
    /// The exact length of [`encode`](Self::encode)'s bytes in `format` when it is known
    /// without encoding (`None`: it is not; the default). With it a transport encodes
    /// the message straight into its payload buffer ([`encode_to_slice`](Self::encode_to_slice))
    /// instead of encoding and copying. The macros give it for `pb` and `postcard`.
    fn encoded_len(&self, format: &str) -> Option<usize> {
        let _ = format;
        None
    }
    /// Writes the message in `format` into `out`, which is exactly as long as
    /// [`encoded_len`](Self::encoded_len) said. The default encodes and copies.
    fn encode_to_slice(&self, format: &str, out: &mut [u8]) -> Result<(), MessageError> {
        copy_to_slice(&self.encode(format)?, Self::type_name(), format, out)
    }
    /// What describes the type in a self-describing recording (MCAP): the macros fill it
    /// in; by default there is none.
    fn schema() -> Schema {
        Schema::NONE
    }
    /// The type's table of operations for other libraries. The message macros give it
    /// as a `static`, so that every use in a library gets the same address (which the
    /// runtime and backends compare first, before the type name); the default is a
    /// constant, which the compiler may copy per code unit. Not for implementing by hand.
    #[doc(hidden)]
    fn __type_support() -> &'static crate::ffi::TypeSupportVtable {
        &const { crate::ffi::channel::table_of::<Self>() }
    }
}

/// A message type's schema, as a recording (MCAP) stores it: `protobuf` with the
/// serialized `FileDescriptorSet` of the type's file and its dependencies, `jsonschema`
/// with a JSON Schema, or none (empty encoding).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Schema {
    /// `protobuf`, `jsonschema`, or empty.
    pub encoding: &'static str,
    /// The schema's name (the full protobuf message name, or the type name).
    pub name: &'static str,
    /// The schema bytes.
    pub data: &'static [u8],
}

impl Schema {
    /// No schema.
    pub const NONE: Schema = Schema {
        encoding: "",
        name: "",
        data: &[],
    };
}

/// `bytes` into `out`, or an error when `encoded_len` and `encode` disagreed on the
/// length (a message changed between the two calls, or a wrong `encoded_len`).
fn copy_to_slice(
    bytes: &[u8],
    type_name: &str,
    format: &str,
    out: &mut [u8],
) -> Result<(), MessageError> {
    if bytes.len() != out.len() {
        return Err(not_encoded(
            type_name,
            format,
            format!("{} bytes encoded into room for {}", bytes.len(), out.len()),
        ));
    }
    out.copy_from_slice(bytes);
    Ok(())
}

/// Why `type_name` could not be encoded as `format`.
pub(crate) fn not_encoded(type_name: &str, format: &str, message: String) -> MessageError {
    MessageError::Serialize {
        type_name: type_name.to_owned(),
        format: format.to_owned(),
        message,
    }
}

/// The formats of serde messages: `postcard` (compact binary, the default) and `json`.
pub const SERDE_FORMATS: &[&str] = &["postcard", "json"];

fn unsupported(type_name: &str, format: &str, formats: &[&str]) -> MessageError {
    MessageError::UnsupportedFormat {
        type_name: type_name.to_owned(),
        format: format.to_owned(),
        supported: formats.join(", "),
    }
}

/// `serialize` of [`serde_message!`](crate::serde_message).
#[doc(hidden)]
pub fn serde_serialize<T: Serialize>(
    msg: &T,
    type_name: &str,
    format: &str,
) -> Result<Vec<u8>, MessageError> {
    let err = |message| not_encoded(type_name, format, message);
    match format {
        "json" => serde_json::to_vec(msg).map_err(|e| err(e.to_string())),
        "postcard" => {
            // Sized first: one allocation of the right size, not a run of doublings.
            let size =
                postcard::experimental::serialized_size(msg).map_err(|e| err(e.to_string()))?;
            postcard::to_extend(msg, Vec::with_capacity(size)).map_err(|e| err(e.to_string()))
        }
        other => Err(unsupported(type_name, other, SERDE_FORMATS)),
    }
}

/// `encoded_len` of [`serde_message!`](crate::serde_message): known for `postcard`.
#[doc(hidden)]
pub fn serde_encoded_len<T: Serialize>(msg: &T, format: &str) -> Option<usize> {
    match format {
        "postcard" => postcard::experimental::serialized_size(msg).ok(),
        _ => None,
    }
}

/// `encode_to_slice` of [`serde_message!`](crate::serde_message).
#[doc(hidden)]
pub fn serde_encode_to_slice<T: Serialize>(
    msg: &T,
    type_name: &str,
    format: &str,
    out: &mut [u8],
) -> Result<(), MessageError> {
    if format == "postcard" {
        let room = out.len();
        let err = |message| not_encoded(type_name, format, message);
        let written = postcard::to_slice(msg, out)
            .map_err(|e| err(format!("{e} (room for {room} bytes)")))?
            .len();
        if written != room {
            return Err(err(format!("{written} bytes encoded into room for {room}")));
        }
        return Ok(());
    }
    copy_to_slice(
        &serde_serialize(msg, type_name, format)?,
        type_name,
        format,
        out,
    )
}

/// `deserialize` of [`serde_message!`](crate::serde_message).
#[doc(hidden)]
pub fn serde_deserialize<T: DeserializeOwned>(
    type_name: &str,
    format: &str,
    bytes: &[u8],
) -> Result<T, MessageError> {
    let err = |message: String| MessageError::Deserialize {
        type_name: type_name.to_owned(),
        format: format.to_owned(),
        message,
    };
    match format {
        "json" => json_deserialize(bytes, false).map_err(err),
        "postcard" => postcard::from_bytes(bytes).map_err(|e| err(e.to_string())),
        other => Err(unsupported(type_name, other, SERDE_FORMATS)),
    }
}

/// Decodes JSON, saying where it stopped: the field (`a.b[2].c`), what was wrong in the
/// words of [`explain_json`](crate::suggest::explain_json) ("did you mean" for an unknown
/// field), and the position; empty input as that.
///
/// With `pb` (a pbjson type), as protobuf's JSON mapping says and AimRT's C++ reader
/// does, a member whose value is `null` reads as absent (the field's default), which
/// pbjson does only for message fields; and the words pbjson's number parsing leaves for
/// a value its field does not take (negative or too large for the field's integer, a
/// fraction, a string that is not a number) are replaced by what the field wants.
///
/// The fast path decodes without tracking the path; only a body that fails is decoded
/// again: from its parsed value with messages' `null` members absent (`pb`,
/// [`NullAsAbsent`](super::proto_json_read::NullAsAbsent)), then with the path tracked.
fn json_deserialize<T: DeserializeOwned>(bytes: &[u8], pb: bool) -> Result<T, String> {
    let plain = match serde_json::from_slice(bytes) {
        Ok(value) => return Ok(value),
        Err(plain) => plain,
    };
    let mut at_a_null = None;
    if pb && plain.is_data() {
        if let Ok(value) = serde_json::from_slice(bytes) {
            let value = super::proto_json_read::NullAsAbsent(value);
            match serde_path_to_error::deserialize::<_, T>(value) {
                Ok(read) => return Ok(read),
                // Read from the parsed value, the error has a path but no position.
                Err(e) => at_a_null = Some(e),
            }
        }
    }
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let e = match serde_path_to_error::deserialize::<_, T>(&mut de) {
        Ok(_) => return Err(de.end().err().unwrap_or(plain).to_string()),
        Err(e) => e,
    };
    // The first error is a null that protobuf reads as absent: what is wrong is past it.
    if let Some(past) = at_a_null.filter(|past| {
        past.path().to_string() != e.path().to_string()
            && e.inner().to_string().starts_with("invalid type: null")
    }) {
        let path = past.path().to_string();
        return Err(describe(&path, &past.into_inner().to_string(), None, pb));
    }
    let path = e.path().to_string();
    let e = e.into_inner();
    let full = e.to_string();
    if e.is_eof()
        && bytes
            .iter()
            .all(|b| matches!(b, b' ' | b'\t' | b'\n' | b'\r'))
    {
        let hint = if pb {
            " ({} is a message with every field at its default)"
        } else {
            ""
        };
        return Err(format!("the input is empty; expected a JSON value{hint}"));
    }
    let at = format!("at line {} column {}", e.line(), e.column());
    let message = full.strip_suffix(&format!(" {at}")).unwrap_or(&full);
    Err(describe(&path, message, Some(&at), pb))
}

/// `at line L column C, field 'a.b[2]': what` ([`json_deserialize`]), from serde's
/// `message` at `path`.
fn describe(path: &str, message: &str, at: Option<&str>, pb: bool) -> String {
    /// What pbjson's number parsing says (its untagged helper, the standard parsers).
    const PBJSON_NUMBER: [&str; 6] = [
        "any variant of untagged enum Content",
        "invalid digit found in string",
        "number too large to fit in target type",
        "number too small to fit in target type",
        "invalid float literal",
        "cannot parse integer from empty string",
    ];
    let what = if pb && PBJSON_NUMBER.iter().any(|m| message.contains(m)) {
        "not a value this field takes: a number in the range of its type, or a string \
         holding one"
            .to_owned()
    } else {
        crate::suggest::explain_json(message)
    };
    // The path of an unknown field ends with the field itself; `?` stands for a place
    // not reached yet (the input ended inside an object, before a key).
    let field = if message.starts_with("unknown field") {
        path.rsplit_once('.').map_or("", |(parent, _)| parent)
    } else {
        path.strip_suffix(".?")
            .or_else(|| path.strip_suffix('?'))
            .unwrap_or(path)
    };
    let field = match field {
        "." | "" => String::new(),
        _ => format!("field '{field}'"),
    };
    match (at, field.is_empty()) {
        (Some(at), true) => format!("{at}: {what}"),
        (Some(at), false) => format!("{at}, {field}: {what}"),
        (None, true) => what,
        (None, false) => format!("{field}: {what}"),
    }
}

/// Implements [`Message`](crate::channel::Message) for a serde type, with the type name
/// `serde:<name>` and the formats `postcard` (default) and `json`.
///
/// ```
/// #[derive(serde::Serialize, serde::Deserialize)]
/// struct Pose { x: f64, y: f64 }
/// aimrt_plugin_api::serde_message!(Pose, "nav.Pose");
/// ```
#[macro_export]
macro_rules! serde_message {
    ($ty:ty, $name:literal) => {
        $crate::__message_impl!(
            $ty,
            concat!("serde:", $name),
            SERDE_FORMATS,
            serde_serialize,
            serde_deserialize,
            serde_encoded_len,
            serde_encode_to_slice,
            $crate::channel::Schema {
                encoding: "jsonschema",
                name: $name,
                data: concat!(
                    "{\"$schema\":\"https://json-schema.org/draft/2020-12/schema\",\"title\":\"",
                    $name,
                    "\",\"type\":\"object\"}"
                )
                .as_bytes(),
            }
        );
    };
}

/// The `Message` impl of [`serde_message!`] and [`prost_message!`]: a type name, a format
/// list and the two functions that encode and decode.
#[doc(hidden)]
#[macro_export]
macro_rules! __message_impl {
    ($ty:ty, $type_name:expr, $formats:ident, $encode:ident, $decode:ident, $len:ident, $to_slice:ident, $schema:expr) => {
        impl $crate::channel::Message for $ty {
            fn __type_support() -> &'static $crate::ffi::TypeSupportVtable {
                // A `static`, not a constant: one address in the library.
                static TABLE: $crate::ffi::TypeSupportVtable = $crate::__private::table_of::<$ty>();
                &TABLE
            }
            fn schema() -> $crate::channel::Schema {
                $schema
            }
            fn type_name() -> &'static str {
                $type_name
            }
            fn formats() -> &'static [&'static str] {
                $crate::channel::$formats
            }
            fn encode(
                &self,
                format: &str,
            ) -> ::std::result::Result<::std::vec::Vec<u8>, $crate::channel::MessageError> {
                $crate::channel::$encode(self, $type_name, format)
            }
            fn decode(
                format: &str,
                bytes: &[u8],
            ) -> ::std::result::Result<Self, $crate::channel::MessageError> {
                $crate::channel::$decode($type_name, format, bytes)
            }
            fn encoded_len(&self, format: &str) -> ::std::option::Option<usize> {
                $crate::channel::$len(self, format)
            }
            fn encode_to_slice(
                &self,
                format: &str,
                out: &mut [u8],
            ) -> ::std::result::Result<(), $crate::channel::MessageError> {
                $crate::channel::$to_slice(self, $type_name, format, out)
            }
        }
    };
}

/// The formats of protobuf messages: `pb` (the default) and `json`, as AimRT.
pub const PB_FORMATS: &[&str] = &["pb", "json"];

/// `encode` of [`prost_message!`](crate::prost_message).
#[cfg(feature = "prost")]
#[doc(hidden)]
pub fn pb_serialize<T: prost::Message + Serialize>(
    msg: &T,
    type_name: &str,
    format: &str,
) -> Result<Vec<u8>, MessageError> {
    match format {
        "pb" => Ok(msg.encode_to_vec()),
        // Doubles and floats as AimRT's protobuf writes them ("NaN", `1`, `1e-09`).
        "json" => super::proto_json::to_vec(msg)
            .map_err(|e| not_encoded(type_name, format, e.to_string())),
        other => Err(unsupported(type_name, other, PB_FORMATS)),
    }
}

/// `encoded_len` of [`prost_message!`](crate::prost_message): known for `pb`.
#[cfg(feature = "prost")]
#[doc(hidden)]
pub fn pb_encoded_len<T: prost::Message>(msg: &T, format: &str) -> Option<usize> {
    (format == "pb").then(|| msg.encoded_len())
}

/// `encode_to_slice` of [`prost_message!`](crate::prost_message).
#[cfg(feature = "prost")]
#[doc(hidden)]
pub fn pb_encode_to_slice<T: prost::Message + Serialize>(
    msg: &T,
    type_name: &str,
    format: &str,
    mut out: &mut [u8],
) -> Result<(), MessageError> {
    if format != "pb" {
        return copy_to_slice(
            &pb_serialize(msg, type_name, format)?,
            type_name,
            format,
            out,
        );
    }
    let room = out.len();
    let err = |message| not_encoded(type_name, format, message);
    msg.encode(&mut out)
        .map_err(|e| err(format!("{e} (room for {room} bytes)")))?;
    match out.len() {
        0 => Ok(()),
        left => Err(err(format!(
            "{} bytes encoded into room for {room}",
            room - left
        ))),
    }
}

/// `decode` of [`prost_message!`](crate::prost_message).
#[cfg(feature = "prost")]
#[doc(hidden)]
pub fn pb_deserialize<T: prost::Message + Default + DeserializeOwned>(
    type_name: &str,
    format: &str,
    bytes: &[u8],
) -> Result<T, MessageError> {
    match format {
        "pb" => T::decode(bytes).map_err(|e| MessageError::Deserialize {
            type_name: type_name.to_owned(),
            format: format.to_owned(),
            message: e.to_string(),
        }),
        "json" => json_deserialize(bytes, true).map_err(|message| MessageError::Deserialize {
            type_name: type_name.to_owned(),
            format: format.to_owned(),
            message,
        }),
        other => Err(unsupported(type_name, other, PB_FORMATS)),
    }
}

/// Implements [`Message`](crate::channel::Message) for a prost-generated protobuf type
/// (feature `prost`), with AimRT's type name `pb:<full name>` and the formats `pb`
/// (default) and `json`. The type must also implement serde's `Serialize` and
/// `Deserialize`: for AimRT's JSON (the proto3 mapping with the `.proto` field names and
/// every field printed, like AimRT's `preserve_proto_field_names` +
/// `always_print_primitive_fields`) generate them with pbjson-build
/// (`preserve_proto_field_names`, `emit_fields`), as `aimrt-protocols` does. Plain serde
/// derives with `#[serde(default)]` also work (64-bit integers are then numbers).
///
/// ```
/// # #[cfg(feature = "prost")] {
/// #[derive(Clone, PartialEq, prost::Message, serde::Serialize, serde::Deserialize)]
/// #[serde(default)]
/// pub struct ExampleEventMsg {
///     #[prost(string, tag = "1")]
///     pub msg: String,
///     #[prost(int32, tag = "2")]
///     pub num: i32,
/// }
/// aimrt_plugin_api::prost_message!(ExampleEventMsg, "aimrt.protocols.example.ExampleEventMsg");
///
/// use aimrt_plugin_api::channel::Message;
/// assert_eq!(ExampleEventMsg::type_name(), "pb:aimrt.protocols.example.ExampleEventMsg");
/// let m = ExampleEventMsg { msg: "count: 1".into(), num: 1 };
/// assert_eq!(m.encode("json").unwrap(), br#"{"msg":"count: 1","num":1}"#);
/// let pb = m.encode("pb").unwrap();
/// assert_eq!(ExampleEventMsg::decode("pb", &pb).unwrap(), m);
/// # }
/// ```
#[cfg(feature = "prost")]
#[macro_export]
macro_rules! prost_message {
    ($ty:ty, $name:literal) => {
        $crate::__message_impl!(
            $ty,
            concat!("pb:", $name),
            PB_FORMATS,
            pb_serialize,
            pb_deserialize,
            pb_encoded_len,
            pb_encode_to_slice,
            $crate::channel::Schema::NONE
        );
    };
    // With the serialized `FileDescriptorSet` of the type's file (what aimrt-codegen
    // writes): the type's schema for recordings.
    ($ty:ty, $name:literal, $descriptors:expr) => {
        $crate::__message_impl!(
            $ty,
            concat!("pb:", $name),
            PB_FORMATS,
            pb_serialize,
            pb_deserialize,
            pb_encoded_len,
            pb_encode_to_slice,
            $crate::channel::Schema {
                encoding: "protobuf",
                name: $name,
                data: $descriptors,
            }
        );
    };
}

/// Includes what `aimrt-codegen` generated for one protobuf package (feature `prost`):
/// the prost types, their JSON (pbjson), their [`Message`] impls and the package's service
/// traits and clients. Use it inside the module that stands for the package.
///
/// ```ignore
/// pub mod example {
///     aimrt_plugin_api::include_proto!("aimrt.protocols.example");
/// }
/// ```
#[cfg(feature = "prost")]
#[macro_export]
macro_rules! include_proto {
    ($package:literal) => {
        include!(concat!(env!("OUT_DIR"), "/", $package, ".rs"));
        include!(concat!(env!("OUT_DIR"), "/", $package, ".serde.rs"));
        include!(concat!(env!("OUT_DIR"), "/", $package, ".aimrt.rs"));
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Sample {
        name: String,
        values: Vec<i64>,
        ratio: f64,
    }
    crate::serde_message!(Sample, "test.Sample");

    #[test]
    fn round_trips_and_errors() {
        let m = Sample {
            name: "ü".into(),
            values: vec![-1, 0, i64::MAX],
            ratio: 0.25,
        };
        for f in Sample::formats() {
            let bytes = m.encode(f).unwrap();
            assert_eq!(Sample::decode(f, &bytes).unwrap(), m, "{f}");
        }
        let e = Sample::decode("json", b"{").unwrap_err();
        assert!(
            e.to_string()
                .contains("cannot deserialize 'serde:test.Sample' from json"),
            "{e}"
        );
        // Where the JSON went wrong: the position, the field, what it wants.
        let e = Sample::decode("json", br#"{"name":"a","values":[1,"x"],"ratio":0.5}"#);
        assert_eq!(
            e.unwrap_err().to_string(),
            "cannot deserialize 'serde:test.Sample' from json: at line 1 column 27, \
             field 'values[1]': expected a whole number, found string \"x\""
        );
        let e = Sample::decode("json", br#"{"nme":"a"}"#)
            .unwrap_err()
            .to_string();
        assert!(
            e.ends_with("at line 1 column 11: the required key 'name' is missing"),
            "{e}"
        );
        let e = Sample::decode("postcard", &[0xff; 3]).unwrap_err();
        assert!(matches!(e, MessageError::Deserialize { .. }), "{e}");
        let e = m.encode("yaml").unwrap_err();
        assert_eq!(
            e.to_string(),
            "message type 'serde:test.Sample' does not support the format 'yaml'; it supports postcard, json"
        );
    }

    #[test]
    fn json_errors_are_in_the_words_of_json() {
        let error = |json: &str| {
            let e = Sample::decode("json", json.as_bytes())
                .unwrap_err()
                .to_string();
            e.strip_prefix("cannot deserialize 'serde:test.Sample' from json: ")
                .unwrap_or_else(|| panic!("{e}"))
                .to_owned()
        };
        for (json, expected) in [
            ("", "the input is empty; expected a JSON value"),
            (" \r\n\t", "the input is empty; expected a JSON value"),
            ("[]", "at line 1 column 2: expected an object or an array of 3 values, found an array of 0"),
            ("5", "at line 1 column 1: expected an object, found integer `5`"),
            ("null", "at line 1 column 4: found null where an object is expected; write a value or remove the key"),
            (r#"{"name":{}}"#, "at line 1 column 8, field 'name': expected a string, found an object"),
            (r#"{"name":null}"#, "at line 1 column 12, field 'name': found null where a string is expected; write a value or remove the key"),
            (r#"{"values":{}}"#, "at line 1 column 10, field 'values': expected an array, found an object"),
            (r#"{"name":"a","name":"b"}"#, "at line 1 column 18: duplicate key 'name'; each key may appear once in an object"),
            // Cut inside an object before its next key: no field to name.
            ("{", "at line 1 column 1: EOF while parsing an object"),
            (r#"{"values":[1,"#, "at line 1 column 13, field 'values': EOF while parsing a value"),
        ] {
            assert_eq!(error(json), expected, "{json:?}");
        }
    }
}
