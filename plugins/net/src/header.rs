//! AimRT's encodings for HTTP: meta key/values as headers ("HttpHeaderEncode"), the
//! `Content-Type` of each serialization type, and the function name's path.

/// AimRT's header encoding: bytes `[A-Za-z0-9-]` stay, every other byte becomes `%XX`
/// (uppercase hex): `aimrt-pub_seq` → `aimrt-pub%5Fseq`.
///
/// ```
/// # use aimrt_net::header::encode;
/// assert_eq!(encode("aimrt-function_name"), "aimrt-function%5Fname");
/// assert_eq!(encode("pb:/a.B/C"), "pb%3A%2Fa%2EB%2FC");
/// ```
pub fn encode(text: &str) -> String {
    const HEX: &[u8; 16] = b"0123456789ABCDEF";
    let mut out = String::with_capacity(text.len() + 8);
    for b in text.bytes() {
        if b.is_ascii_alphanumeric() || b == b'-' {
            out.push(char::from(b));
        } else {
            out.push('%');
            out.push(char::from(HEX[usize::from(b >> 4)]));
            out.push(char::from(HEX[usize::from(b & 0xF)]));
        }
    }
    out
}

/// Decodes `%XX` escapes (hex in either case). Unlike AimRT, a malformed escape is kept
/// as written instead of turning into a zero byte; invalid UTF-8 is replaced.
///
/// ```
/// # use aimrt_net::header::decode;
/// assert_eq!(decode(b"aimrt-function%5fname"), "aimrt-function_name");
/// assert_eq!(decode(b"100%"), "100%");
/// assert_eq!(decode(b"%zz"), "%zz");
/// ```
pub fn decode(bytes: &[u8]) -> String {
    if !bytes.contains(&b'%') {
        return String::from_utf8_lossy(bytes).into_owned();
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
    String::from_utf8_lossy(&out).into_owned()
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

/// Headers that are HTTP's own, never meta: the server skips them when it copies the
/// request's headers into the call's context, and the client never sends meta under
/// their names.
pub fn is_standard(name: &str) -> bool {
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
}
