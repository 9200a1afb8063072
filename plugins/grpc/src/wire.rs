//! gRPC on HTTP/2, as far as unary calls need it (gRPC's `PROTOCOL-HTTP2.md`): a message is
//! a 5-byte prefix (compressed flag, length as a big-endian u32) and the message; the
//! deadline travels in `grpc-timeout` (at most 8 digits and a unit); the outcome in the
//! `grpc-status` and `grpc-message` trailers (or headers, for an answer without a body).

use std::time::Duration;

use aimrt_plugin_api::RpcStatus;

/// The length of a message's prefix.
pub const PREFIX: usize = 5;

/// The header (or trailer) with AimRT's status code of a failed call, next to
/// `grpc-status` (ours; AimRT's client reads only `grpc-status`).
pub const AIMRT_STATUS: &str = "aimrt-rs-status";

/// `message` with its prefix (not compressed).
///
/// ```
/// assert_eq!(aimrt_grpc::wire::frame(b"hi"), [0, 0, 0, 0, 2, b'h', b'i']);
/// ```
pub fn frame(message: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(PREFIX + message.len());
    out.push(0);
    out.extend_from_slice(
        &u32::try_from(message.len())
            .unwrap_or(u32::MAX)
            .to_be_bytes(),
    );
    out.extend_from_slice(message);
    out
}

/// Why a body is not one gRPC message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FrameError {
    /// Fewer bytes than a prefix.
    Short(usize),
    /// The compressed flag is set (this plugin, like AimRT's, compresses nothing).
    Compressed,
    /// The prefix's length and the bytes after it differ (a cut message, or more than one).
    Length {
        /// What the prefix says.
        said: u64,
        /// The bytes after the prefix.
        got: u64,
    },
}

impl std::fmt::Display for FrameError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FrameError::Short(n) => write!(
                f,
                "the body has {n} bytes, fewer than a gRPC message's 5-byte prefix"
            ),
            FrameError::Compressed => f.write_str(
                "the message is compressed (grpc-encoding); this server takes uncompressed messages only",
            ),
            FrameError::Length { said, got } => write!(
                f,
                "the gRPC prefix says {said} bytes and {got} follow; a unary call carries exactly one message"
            ),
        }
    }
}

/// The one message of `body`.
///
/// ```
/// use aimrt_grpc::wire::{unframe, FrameError};
/// assert_eq!(unframe(&[0, 0, 0, 0, 2, b'h', b'i']), Ok(&b"hi"[..]));
/// assert_eq!(unframe(&[0, 0, 0, 0, 3, b'h', b'i']), Err(FrameError::Length { said: 3, got: 2 }));
/// assert_eq!(unframe(&[1, 0, 0, 0, 0]), Err(FrameError::Compressed));
/// assert_eq!(unframe(&[0, 0]), Err(FrameError::Short(2)));
/// ```
pub fn unframe(body: &[u8]) -> Result<&[u8], FrameError> {
    let Some((prefix, message)) = body.split_first_chunk::<PREFIX>() else {
        return Err(FrameError::Short(body.len()));
    };
    let said = u32::from_be_bytes([prefix[1], prefix[2], prefix[3], prefix[4]]);
    if prefix[0] != 0 {
        return Err(FrameError::Compressed);
    }
    if u64::from(said) != message.len() as u64 {
        return Err(FrameError::Length {
            said: u64::from(said),
            got: message.len() as u64,
        });
    }
    Ok(message)
}

/// The `grpc-timeout` header's name.
pub static GRPC_TIMEOUT: hyper::header::HeaderName =
    hyper::header::HeaderName::from_static("grpc-timeout");

/// `timeout` as `grpc-timeout`: the finest unit whose value has at most 8 digits, rounded
/// up (AimRT writes nanoseconds of any length, which the protocol does not allow).
/// Written without formatting machinery or 128-bit division: it is per call.
///
/// ```
/// use std::time::Duration;
/// use aimrt_grpc::wire::timeout_header;
/// assert_eq!(timeout_header(Duration::from_millis(5)), "5000000n");
/// assert_eq!(timeout_header(Duration::from_secs(5)), "5000000u");
/// assert_eq!(timeout_header(Duration::from_nanos(100_000_001)), "100001u");
/// assert_eq!(timeout_header(Duration::from_secs(3600 * 24 * 365)), "31536000S");
/// assert_eq!(timeout_header(Duration::from_secs(3600 * 24 * 365 * 10)), "5256000M");
/// ```
pub fn timeout_header(timeout: Duration) -> hyper::header::HeaderValue {
    let mut text = [0; 9];
    // Digits and a letter are always a header value; the fallback is never taken.
    hyper::header::HeaderValue::from_bytes(timeout_text(timeout, &mut text))
        .unwrap_or_else(|_| hyper::header::HeaderValue::from_static("99999999H"))
}

/// The text of [`timeout_header`], written into the end of `out`.
fn timeout_text(timeout: Duration, out: &mut [u8; 9]) -> &[u8] {
    const MAX: u64 = 99_999_999;
    const UNITS: [(u8, u64); 6] = [
        (b'n', 1),
        (b'u', 1_000),
        (b'm', 1_000_000),
        (b'S', 1_000_000_000),
        (b'M', 60_000_000_000),
        (b'H', 3_600_000_000_000),
    ];
    let (mut value, unit) = match u64::try_from(timeout.as_nanos()) {
        Ok(ns) => UNITS
            .iter()
            .find_map(|&(unit, per)| {
                let value = ns.div_ceil(per);
                (value <= MAX).then_some((value, unit))
            })
            .unwrap_or((MAX, b'H')),
        // Over 584 years: only hours can have 8 digits.
        Err(_) => {
            let hours = timeout.as_nanos().div_ceil(3_600_000_000_000);
            (u64::try_from(hours).map_or(MAX, |h| h.min(MAX)), b'H')
        }
    };
    // At most 8 digits, so they fit before the unit.
    let mut at = 8;
    out[at] = unit;
    loop {
        at -= 1;
        out[at] = b'0' + (value % 10) as u8;
        value /= 10;
        if value == 0 {
            return &out[at..];
        }
    }
}

/// A `grpc-timeout` value as a duration; `None` when it is not digits and one of the
/// units `H`, `M`, `S`, `m`, `u`, `n` (more than 8 digits are read, as AimRT writes them).
///
/// ```
/// use std::time::Duration;
/// use aimrt_grpc::wire::parse_timeout;
/// assert_eq!(parse_timeout("1S"), Some(Duration::from_secs(1)));
/// assert_eq!(parse_timeout("5000000000n"), Some(Duration::from_secs(5)));
/// assert_eq!(parse_timeout("10x"), None);
/// assert_eq!(parse_timeout("S"), None);
/// ```
pub fn parse_timeout(text: &str) -> Option<Duration> {
    let text = text.trim();
    let unit = text.chars().last()?;
    let digits = &text[..text.len() - unit.len_utf8()];
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let value: u64 = digits.parse().ok()?;
    let per: u64 = match unit {
        'n' => 1,
        'u' => 1_000,
        'm' => 1_000_000,
        'S' => 1_000_000_000,
        'M' => 60_000_000_000,
        'H' => 3_600_000_000_000,
        _ => return None,
    };
    Some(Duration::from_nanos(value.saturating_mul(per)))
}

/// The serialization type of a request's `content-type` (AimRT's table, parameters
/// ignored): `application/grpc` and `application/grpc+proto` are `pb`,
/// `application/grpc+json` is `json`, `application/grpc+ros2` is `ros2`.
///
/// ```
/// use aimrt_grpc::wire::serialization_of;
/// assert_eq!(serialization_of("application/grpc"), Some("pb"));
/// assert_eq!(serialization_of("application/grpc+json; charset=utf-8"), Some("json"));
/// assert_eq!(serialization_of("application/json"), None);
/// ```
pub fn serialization_of(content_type: &str) -> Option<&'static str> {
    let media = content_type
        .split([';', ' '])
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    match media.as_str() {
        "application/grpc" | "application/grpc+proto" => Some("pb"),
        "application/grpc+json" => Some("json"),
        "application/grpc+ros2" => Some("ros2"),
        _ => None,
    }
}

/// The `content-type` of a call in `format`; `None` for a format gRPC here does not carry.
pub fn content_type_of(format: &str) -> Option<&'static str> {
    match format {
        "pb" => Some("application/grpc"),
        "json" => Some("application/grpc+json"),
        "ros2" => Some("application/grpc+ros2"),
        _ => None,
    }
}

/// gRPC's status codes this plugin answers and reads.
pub mod code {
    /// Success.
    pub const OK: u32 = 0;
    /// The server failed in a way that fits no other code.
    pub const UNKNOWN: u32 = 2;
    /// The request cannot be read.
    pub const INVALID_ARGUMENT: u32 = 3;
    /// The deadline passed.
    pub const DEADLINE_EXCEEDED: u32 = 4;
    /// Nothing by that name.
    pub const NOT_FOUND: u32 = 5;
    /// The server is overloaded.
    pub const RESOURCE_EXHAUSTED: u32 = 8;
    /// No such method, or not in this form.
    pub const UNIMPLEMENTED: u32 = 12;
    /// The server broke.
    pub const INTERNAL: u32 = 13;
    /// The server cannot take the call now.
    pub const UNAVAILABLE: u32 = 14;
}

/// The gRPC code of an AimRT status a service answered.
///
/// ```
/// use aimrt_grpc::wire::grpc_code_of;
/// use aimrt_plugin_api::RpcStatus;
/// assert_eq!(grpc_code_of(RpcStatus::OK), 0);
/// assert_eq!(grpc_code_of(RpcStatus::SVR_NOT_FOUND), 12);
/// assert_eq!(grpc_code_of(RpcStatus::TIMEOUT), 4);
/// ```
pub fn grpc_code_of(status: RpcStatus) -> u32 {
    match status.code() {
        0 => code::OK,
        2 => code::DEADLINE_EXCEEDED,
        1002 | 1003 => code::UNIMPLEMENTED,
        1004 | 1006 | 1007 => code::INVALID_ARGUMENT,
        1009 => code::UNAVAILABLE,
        1008 | 1 | 1000 => code::UNKNOWN,
        _ => code::INTERNAL,
    }
}

/// The AimRT status of a gRPC code a server answered without AimRT's own code (a server
/// that is not aimrt-rs). AimRT's client answers 2000 (`CLI_UNKNOWN`) to every failure.
///
/// ```
/// use aimrt_grpc::wire::status_of_grpc;
/// use aimrt_plugin_api::RpcStatus;
/// assert_eq!(status_of_grpc(4), RpcStatus::TIMEOUT);
/// assert_eq!(status_of_grpc(12), RpcStatus::SVR_NOT_FOUND);
/// assert_eq!(status_of_grpc(7), RpcStatus::SVR_HANDLE_FAILED);
/// ```
pub fn status_of_grpc(grpc: u32) -> RpcStatus {
    match grpc {
        code::OK => RpcStatus::OK,
        code::DEADLINE_EXCEEDED => RpcStatus::TIMEOUT,
        code::UNIMPLEMENTED | code::NOT_FOUND => RpcStatus::SVR_NOT_FOUND,
        code::INVALID_ARGUMENT => RpcStatus::SVR_DESERIALIZATION_FAILED,
        code::UNAVAILABLE | code::RESOURCE_EXHAUSTED => RpcStatus::SVR_NOT_READY,
        code::INTERNAL => RpcStatus::SVR_BACKEND_INTERNAL_ERROR,
        _ => RpcStatus::SVR_HANDLE_FAILED,
    }
}

/// `text` as `grpc-message` carries it: bytes outside printable ASCII, and `%`,
/// percent-encoded.
///
/// ```
/// use aimrt_grpc::wire::{decode_message, encode_message};
/// assert_eq!(encode_message("50% done\n"), "50%25 done%0A");
/// assert_eq!(decode_message("50%25 done%0A"), "50% done\n");
/// assert_eq!(decode_message("bad %zz"), "bad %zz");
/// ```
pub fn encode_message(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for b in text.bytes() {
        if (0x20..=0x7e).contains(&b) && b != b'%' {
            out.push(char::from(b));
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// A `grpc-message` as text (a malformed escape is kept as is, as the protocol asks).
pub fn decode_message(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' && i + 2 < bytes.len() {
            let hex = std::str::from_utf8(&bytes[i + 1..i + 3]).ok();
            if let Some(b) = hex.and_then(|h| u8::from_str_radix(h, 16).ok()) {
                out.push(b);
                i += 3;
                continue;
            }
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timeouts_round_trip_in_at_most_eight_digits() {
        for d in [
            Duration::from_nanos(1),
            Duration::from_nanos(99_999_999),
            Duration::from_millis(100),
            Duration::from_secs(1),
            Duration::from_secs(59),
            Duration::from_secs(3600),
            Duration::from_secs(10 * 365 * 24 * 3600),
        ] {
            let header = timeout_header(d);
            let text = header.to_str().unwrap();
            assert!(text.len() <= 9, "{text}");
            let back = parse_timeout(text).unwrap();
            assert!(back >= d, "{d:?} -> {text} -> {back:?}: never shorter");
            assert!(
                back - d < d / 1000 + Duration::from_micros(1),
                "{d:?} -> {back:?}"
            );
        }
    }

    /// The digits written by hand are those of the plain 128-bit computation, at each
    /// unit's edges and beyond 584 years.
    #[test]
    fn timeouts_are_written_as_the_plain_computation_would() {
        fn plain(timeout: Duration) -> String {
            let ns = timeout.as_nanos();
            for (unit, per) in [
                ('n', 1u128),
                ('u', 1_000),
                ('m', 1_000_000),
                ('S', 1_000_000_000),
                ('M', 60_000_000_000),
                ('H', 3_600_000_000_000),
            ] {
                let value = ns.div_ceil(per);
                if value <= 99_999_999 {
                    return format!("{value}{unit}");
                }
            }
            "99999999H".to_owned()
        }
        let mut cases = vec![
            Duration::ZERO,
            Duration::MAX,
            Duration::from_secs(u64::MAX / 2),
        ];
        for per in [
            1u64,
            1_000,
            1_000_000,
            1_000_000_000,
            60_000_000_000,
            3_600_000_000_000,
        ] {
            for edge in [99_999_999u64, 100_000_000] {
                let ns = u128::from(per) * u128::from(edge);
                for ns in [ns - 1, ns, ns + 1] {
                    let secs = u64::try_from(ns / 1_000_000_000).unwrap();
                    cases.push(Duration::new(secs, (ns % 1_000_000_000) as u32));
                }
            }
        }
        cases.push(Duration::from_nanos(u64::MAX));
        cases.push(Duration::from_nanos(u64::MAX) + Duration::from_nanos(1));
        for d in cases {
            assert_eq!(timeout_header(d), plain(d).as_str(), "{d:?}");
        }
    }

    #[test]
    fn every_aimrt_status_has_a_grpc_code_that_reads_back_to_its_kind() {
        for code in [
            0, 1, 2, 1000, 1001, 1002, 1003, 1004, 1005, 1006, 1007, 1008, 1009,
        ] {
            let status = RpcStatus::from_code(code);
            let back = status_of_grpc(grpc_code_of(status));
            assert_eq!(back.is_ok(), status.is_ok(), "{code}");
            assert_eq!(back.is_timeout(), status.is_timeout(), "{code}");
        }
    }

    #[test]
    fn garbage_is_a_frame_error_never_a_panic() {
        for body in [
            &[][..],
            &[0],
            &[0, 0, 0, 0],
            &[0, 255, 255, 255, 255],
            &[2, 0, 0, 0, 0, 1],
        ] {
            assert!(unframe(body).is_err(), "{body:?}");
        }
        assert_eq!(decode_message("%"), "%");
        assert_eq!(decode_message("%4"), "%4");
        assert_eq!(decode_message("%41"), "A");
        assert_eq!(decode_message("%E6%97%A5"), "日");
    }
}
