//! AimRT's encodings for HTTP: meta key/values as headers ("HttpHeaderEncode"), the
//! `Content-Type` of each serialization type, and the function name's path.

use std::borrow::Cow;

use aimrt_plugin_api::ffi::lossy;
use hyper::header::{HeaderMap, HeaderName, HeaderValue};

/// Whether AimRT's header encoding keeps `b` as it is.
fn plain(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b == b'-'
}

/// AimRT's header encoding: bytes `[A-Za-z0-9-]` stay, every other byte becomes `%XX`
/// (uppercase hex): `aimrt-pub_seq` → `aimrt-pub%5Fseq`. Borrowed when nothing needs
/// escaping.
///
/// ```
/// # use aimrt_net::header::encode;
/// assert_eq!(encode("aimrt-function_name"), "aimrt-function%5Fname");
/// assert_eq!(encode("pb:/a.B/C"), "pb%3A%2Fa%2EB%2FC");
/// assert!(matches!(encode("42"), std::borrow::Cow::Borrowed("42")));
/// ```
pub fn encode(text: &str) -> Cow<'_, str> {
    const HEX: &[u8; 16] = b"0123456789ABCDEF";
    if text.bytes().all(plain) {
        return Cow::Borrowed(text);
    }
    let mut out = Vec::with_capacity(text.len() + 16);
    for b in text.bytes() {
        if plain(b) {
            out.push(b);
        } else {
            out.extend_from_slice(&[b'%', HEX[usize::from(b >> 4)], HEX[usize::from(b & 0xF)]]);
        }
    }
    // Every byte pushed is ASCII.
    Cow::Owned(String::from_utf8(out).unwrap_or_default())
}

/// Decodes `%XX` escapes (hex in either case). Unlike AimRT, a malformed escape is kept
/// as written instead of turning into a zero byte; invalid UTF-8 is replaced. Borrowed
/// when there is nothing to decode.
///
/// ```
/// # use aimrt_net::header::decode;
/// assert_eq!(decode(b"aimrt-function%5fname"), "aimrt-function_name");
/// assert_eq!(decode(b"100%"), "100%");
/// assert_eq!(decode(b"%zz"), "%zz");
/// ```
pub fn decode(bytes: &[u8]) -> Cow<'_, str> {
    if !bytes.contains(&b'%') {
        return lossy(bytes);
    }
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let b = bytes[i];
        if b == b'%' && i + 2 < bytes.len() {
            let hex = |c: u8| char::from(c).to_digit(16);
            if let (Some(h), Some(l)) = (hex(bytes[i + 1]), hex(bytes[i + 2])) {
                out.push((h * 16 + l) as u8);
                i += 3;
                continue;
            }
        }
        out.push(b);
        i += 1;
    }
    Cow::Owned(lossy(&out).into_owned())
}

/// AimRT's header with a call's timeout in whole seconds.
pub(crate) const TIMEOUT: HeaderName = HeaderName::from_static("timeout");

/// The header AimRT's server sets on each request to the client's address; a client's
/// own is dropped.
pub(crate) const REMOTE_ENDPOINT: HeaderName = HeaderName::from_static("remote-endpoint");

/// The context key under which a server hands on the client's address (`ip:port`), as
/// AimRT's server does.
pub(crate) const REMOTE_ENDPOINT_KEY: &str = "Remote-Endpoint";

/// The header of `aimrt-function_name`.
pub(crate) const FUNCTION_NAME: HeaderName = HeaderName::from_static("aimrt-function%5fname");

/// The header that carries the AimRT status code of every answer (ours; AimRT's server
/// answers 500 for every failure, and its client reports 1003 for any non-200).
pub(crate) const STATUS_HEADER: HeaderName = HeaderName::from_static("aimrt-rs-status");

/// The framework's meta keys and their header names (AimRT's encoding, lowercased as
/// HTTP/1 carries names), built at compile time: `HeaderName::from_static` called at run
/// time would check its text on every message.
static KNOWN: [(&str, HeaderName); 10] = [
    ("aimrt-function_name", FUNCTION_NAME),
    (
        "aimrt-request_id",
        HeaderName::from_static("aimrt-request%5fid"),
    ),
    (
        "aimrt-response_id",
        HeaderName::from_static("aimrt-response%5fid"),
    ),
    (
        "aimrt-serialization_type",
        HeaderName::from_static("aimrt-serialization%5ftype"),
    ),
    ("aimrt-backend", HeaderName::from_static("aimrt-backend")),
    ("aimrt-to_addr", HeaderName::from_static("aimrt-to%5faddr")),
    (
        "aimrt-from_pkg",
        HeaderName::from_static("aimrt-from%5fpkg"),
    ),
    (
        "aimrt-from_module",
        HeaderName::from_static("aimrt-from%5fmodule"),
    ),
    ("aimrt-pub_seq", HeaderName::from_static("aimrt-pub%5fseq")),
    ("aimrt-pub_ts", HeaderName::from_static("aimrt-pub%5fts")),
];

/// The header name that carries meta key `key`; `None` when the encoded key is not a
/// valid header name.
pub fn header_name(key: &str) -> Option<HeaderName> {
    match KNOWN.iter().find(|(k, _)| *k == key) {
        Some((_, name)) => Some(name.clone()),
        None => HeaderName::from_bytes(encode(key).as_bytes()).ok(),
    }
}

/// The meta key a header name carries (names arrive lowercased).
pub fn meta_key(name: &str) -> Cow<'_, str> {
    match KNOWN.iter().find(|(_, n)| n.as_str() == name) {
        Some((key, _)) => Cow::Borrowed(key),
        None => decode(name.as_bytes()),
    }
}

/// Adds each meta pair as a header, in AimRT's encoding, skipping keys that are HTTP's
/// own ([`is_standard`]) and pairs that cannot be a header.
pub fn put_meta<'a>(headers: &mut HeaderMap, pairs: impl IntoIterator<Item = (&'a str, &'a str)>) {
    for (k, v) in pairs {
        put_pair(headers, k, v);
    }
}

/// Adds one meta pair as [`put_meta`] does.
pub fn put_pair(headers: &mut HeaderMap, key: &str, value: &str) {
    if is_standard(key) {
        return;
    }
    if let (Some(name), Ok(value)) = (header_name(key), HeaderValue::from_str(&encode(value))) {
        headers.insert(name, value);
    }
}

/// The `Content-Type` of a serialization type, as AimRT's.
pub fn content_type(serialization_type: &str) -> Option<&'static str> {
    match serialization_type {
        "pb" => Some("application/protobuf"),
        "json" => Some("application/json"),
        "ros2" => Some("application/ros2"),
        _ => None,
    }
}

pub use aimrt_wire::name_without_prefix;

/// [`is_standard`] for a parsed header name: HTTP's commonest headers by their parsed
/// identity, without comparing text.
pub fn is_standard_name(name: &HeaderName) -> bool {
    use hyper::header::{CONTENT_LENGTH, CONTENT_TYPE, HOST, USER_AGENT};
    name == HOST
        || name == CONTENT_TYPE
        || name == CONTENT_LENGTH
        || name == USER_AGENT
        || is_standard(name.as_str())
}

/// Headers that are HTTP's own, never meta: the server skips them when it copies the
/// request's headers into the call's context, and the client never sends meta under
/// their names.
pub fn is_standard(name: &str) -> bool {
    // Most meta is the framework's own.
    if name.starts_with("aimrt-") {
        return false;
    }
    // Header names arrive lowercased (hyper); others are compared case-insensitively.
    let lower;
    let name = if name.bytes().any(|b| b.is_ascii_uppercase()) {
        lower = name.to_ascii_lowercase();
        lower.as_str()
    } else {
        name
    };
    matches!(
        name,
        "host"
            | "user-agent"
            | "timeout"
            | "content-type"
            | "content-length"
            | "connection"
            | "keep-alive"
            | "accept"
            | "accept-encoding"
            | "accept-language"
            | "transfer-encoding"
            | "te"
            | "trailer"
            | "upgrade"
            | "expect"
            | "proxy-connection"
            | "proxy-authorization"
            | "authorization"
            | "origin"
            | "referer"
            | "cookie"
            | "cache-control"
            | "pragma"
            | "date"
            | "via"
            | "x-requested-with"
            | "access-control-request-method"
            | "access-control-request-headers"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_every_byte_and_keeps_aimrts_spelling() {
        let all: String = (1u8..=127).map(char::from).collect();
        assert_eq!(decode(encode(&all).as_bytes()), all);
        assert_eq!(decode(encode("ü €").as_bytes()), "ü €");
        // The golden request of AimRT's client.
        assert_eq!(
            encode("pb:/aimrt.protocols.example.ExampleService/GetFooData"),
            "pb%3A%2Faimrt%2Eprotocols%2Eexample%2EExampleService%2FGetFooData"
        );
        assert_eq!(decode(b"%4"), "%4");
        assert_eq!(decode(b"a%"), "a%");
        assert!(is_standard("Content-Length") && !is_standard("aimrt-backend"));
    }

    #[test]
    fn known_names_are_the_encoded_keys() {
        for (key, name) in &KNOWN {
            let name = name.as_str();
            assert_eq!(encode(key).to_ascii_lowercase(), name);
            assert_eq!(header_name(key).unwrap().as_str(), name);
            assert_eq!(meta_key(name), *key);
        }
        assert_eq!(header_name("aimrt-function_name"), Some(FUNCTION_NAME));
        assert_eq!(header_name("my key").unwrap().as_str(), "my%20key");
        assert_eq!(meta_key("my%20key"), "my key");
        let mut h = HeaderMap::new();
        put_meta(
            &mut h,
            [("host", "x"), ("aimrt-to_addr", "http://a:1"), ("k", "v")],
        );
        assert_eq!(h.len(), 2);
        assert_eq!(h["aimrt-to%5faddr"], "http%3A%2F%2Fa%3A1");
        assert_eq!(h["k"], "v");
    }
}
