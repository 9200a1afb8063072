//! AimRT zenoh_plugin's key expressions and payloads.
//!
//! - Channel key: `channel/<UrlEncode(topic)>/<UrlEncode(type)>[/<limit_domain>]`.
//! - RPC pattern `P`: `aimrt_rpc/<UrlEncode(name without prefix)>[/<limit_domain>]`; requests
//!   go to `req/P`, answers to `rsp/P`.
//! - Every payload starts with `u32_le` = the byte count of the rest; readers honour it
//!   (bytes after it are ignored: a shared-memory loan may be longer than the message).
//!
//! | payload  | after the length |
//! |----------|------------------|
//! | channel  | `str8` serialization type, meta, message |
//! | request  | `str8` serialization type, `str8` P, 4 bytes request id, meta, request |
//! | response | `str8` serialization type, the 4 request id bytes, `u32_le` status, response |
//!
//! The fields after the length are [`aimrt_wire::payload`]'s (mqtt_plugin's payloads have
//! no prefix). AimRT sends an error response (status ≠ 0) without the length prefix;
//! [`decode_response`] reads both forms, [`encode_response`] always writes the prefixed one.

use aimrt_wire::payload::{channel_header_len, put_channel_header};
pub use aimrt_wire::payload::{ChannelView, Request, Response};
use aimrt_wire::{url_encode, Reader, WireError};

/// `"/" + limit_domain`, or empty when none is set.
pub fn domain_suffix(limit_domain: &str) -> String {
    if limit_domain.is_empty() {
        String::new()
    } else {
        format!("/{limit_domain}")
    }
}

/// The key of a topic and message type.
///
/// ```
/// # use aimrt_zenoh::wire::channel_key;
/// assert_eq!(
///     channel_key("test_topic", "pb:aimrt.protocols.example.ExampleEventMsg", "room1/A2"),
///     "channel/test_topic/pb%3Aaimrt.protocols.example.ExampleEventMsg/room1/A2"
/// );
/// ```
pub fn channel_key(topic: &str, msg_type: &str, limit_domain: &str) -> String {
    format!(
        "channel/{}/{}{}",
        url_encode(topic),
        url_encode(msg_type),
        domain_suffix(limit_domain)
    )
}

/// The RPC pattern `P` of a function (`req/P` carries requests, `rsp/P` answers).
///
/// ```
/// # use aimrt_zenoh::wire::rpc_pattern;
/// assert_eq!(
///     rpc_pattern("pb:/aimrt.protocols.example.ExampleService/GetFooData", ""),
///     "aimrt_rpc/%2Faimrt.protocols.example.ExampleService%2FGetFooData"
/// );
/// ```
pub fn rpc_pattern(func: &str, limit_domain: &str) -> String {
    format!(
        "aimrt_rpc/{}{}",
        url_encode(aimrt_wire::name_without_prefix(func)),
        domain_suffix(limit_domain)
    )
}

/// Why a payload cannot be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PayloadError {
    /// A field is cut, not UTF-8, or too long for its prefix.
    #[error(transparent)]
    Field(#[from] WireError),
    /// The length prefix says more than the payload holds.
    #[error("the length prefix says {said} bytes follow, but only {have} do")]
    LengthBeyondPayload {
        /// What the prefix says.
        said: usize,
        /// What follows it.
        have: usize,
    },
    /// The whole payload is larger than a `u32` length can say.
    #[error("the payload is {0} bytes; AimRT's u32 length prefix allows at most 4 GiB")]
    TooLarge(usize),
}

/// The bytes the length prefix covers.
fn framed(bytes: &[u8]) -> Result<&[u8], PayloadError> {
    let mut r = Reader::new(bytes);
    let said = r.u32("length prefix")? as usize;
    let rest = r.rest();
    if said > rest.len() {
        return Err(PayloadError::LengthBeyondPayload {
            said,
            have: rest.len(),
        });
    }
    Ok(&rest[..said])
}

/// `write` behind a length prefix that it then covers.
fn prefixed(
    capacity: usize,
    write: impl FnOnce(&mut Vec<u8>) -> Result<(), WireError>,
) -> Result<Vec<u8>, PayloadError> {
    let mut out = Vec::with_capacity(4 + capacity);
    out.extend_from_slice(&[0; 4]);
    write(&mut out)?;
    end_channel(&mut out, 0)?;
    Ok(out)
}

fn meta_iter(meta: &[(String, String)]) -> impl Iterator<Item = (&String, &String)> + Clone {
    meta.iter().map(|(k, v)| (k, v))
}

/// One channel message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelPayload {
    /// `pb`, `json`, …
    pub serialization_type: String,
    /// The context's meta, in wire order.
    pub meta: Vec<(String, String)>,
    /// The encoded message.
    pub message: Vec<u8>,
}

impl ChannelPayload {
    /// The payload bytes.
    pub fn encode(&self) -> Result<Vec<u8>, PayloadError> {
        encode_channel(
            &self.serialization_type,
            meta_iter(&self.meta),
            &self.message,
        )
    }

    /// Reads a payload; trailing bytes after the prefixed length are ignored.
    pub fn decode(bytes: &[u8]) -> Result<ChannelPayload, PayloadError> {
        let v = decode_channel(bytes)?;
        Ok(ChannelPayload {
            serialization_type: v.serialization_type.to_owned(),
            meta: v
                .meta
                .into_iter()
                .map(|(k, v)| (k.to_owned(), v.to_owned()))
                .collect(),
            message: v.message.to_vec(),
        })
    }
}

/// Reads a channel payload in place (the receive path: the message is not copied);
/// trailing bytes after the prefixed length are ignored.
pub fn decode_channel(bytes: &[u8]) -> Result<ChannelView<'_>, PayloadError> {
    Ok(ChannelView::read(framed(bytes)?)?)
}

/// The bytes of a channel payload before its message, for a message of `message_len`
/// bytes (the publish path sends the two without joining them).
pub fn channel_header<K: AsRef<[u8]>, V: AsRef<[u8]>>(
    serialization_type: &str,
    meta: impl IntoIterator<Item = (K, V)> + Clone,
    message_len: usize,
) -> Result<Vec<u8>, PayloadError> {
    let mut out = begin_channel(serialization_type, meta, 0)?;
    end_channel(&mut out, message_len)?;
    Ok(out)
}

/// A channel payload's header with room for `room` more bytes, for the message to be
/// written behind it; [`end_channel`] then sets the length prefix. One buffer, no copy
/// of the message beyond its encoding.
///
/// ```
/// use aimrt_zenoh::wire::{begin_channel, channel_header, end_channel};
/// let mut out = begin_channel("pb", [("k", "v")], 16).unwrap();
/// out.extend_from_slice(b"message");
/// end_channel(&mut out, 0).unwrap();
/// let mut expected = channel_header("pb", [("k", "v")], 7).unwrap();
/// expected.extend_from_slice(b"message");
/// assert_eq!(out, expected);
/// ```
pub fn begin_channel<K: AsRef<[u8]>, V: AsRef<[u8]>>(
    serialization_type: &str,
    meta: impl IntoIterator<Item = (K, V)> + Clone,
    room: usize,
) -> Result<Vec<u8>, PayloadError> {
    let mut out =
        Vec::with_capacity(4 + channel_header_len(serialization_type, meta.clone()) + room);
    out.extend_from_slice(&[0; 4]);
    put_channel_header(&mut out, serialization_type, meta)?;
    Ok(out)
}

/// Sets the length prefix of a payload [`begin_channel`] began to what follows it in
/// `out` and the `more` bytes that will follow `out` (the message, when it is copied
/// behind the header elsewhere, e.g. into shared memory).
pub fn end_channel(out: &mut [u8], more: usize) -> Result<(), PayloadError> {
    let len = out.len().saturating_sub(4).saturating_add(more);
    let len32 = u32::try_from(len).map_err(|_| PayloadError::TooLarge(len))?;
    if let Some(prefix) = out.get_mut(..4) {
        prefix.copy_from_slice(&len32.to_le_bytes());
    }
    Ok(())
}

/// A whole channel payload from borrowed parts.
pub fn encode_channel<K: AsRef<[u8]>, V: AsRef<[u8]>>(
    serialization_type: &str,
    meta: impl IntoIterator<Item = (K, V)> + Clone,
    message: &[u8],
) -> Result<Vec<u8>, PayloadError> {
    let mut out = channel_header(serialization_type, meta, message.len())?;
    out.extend_from_slice(message);
    Ok(out)
}

/// A request's payload bytes (`reply_to` is the RPC pattern the answer goes to, as
/// `rsp/<pattern>`).
pub fn encode_request(request: &Request) -> Result<Vec<u8>, PayloadError> {
    prefixed(request.encoded_len(), |out| request.write_to(out))
}

/// Reads a request; trailing bytes after the prefixed length are ignored.
pub fn decode_request(bytes: &[u8]) -> Result<Request, PayloadError> {
    Ok(Request::read(framed(bytes)?)?)
}

/// An answer's payload bytes, always length-prefixed (also for an error status, where
/// AimRT leaves the prefix out).
pub fn encode_response(response: &Response) -> Result<Vec<u8>, PayloadError> {
    prefixed(response.encoded_len(), |out| response.write_to(out))
}

/// Reads an answer in either of AimRT's forms: length-prefixed, or (AimRT's error
/// replies) `str8 type | id | u32 status` with no prefix.
pub fn decode_response(bytes: &[u8]) -> Result<Response, PayloadError> {
    let prefixed = framed(bytes).and_then(|inner| Ok(Response::read(inner)?));
    match prefixed {
        Ok(r) => Ok(r),
        // Only an error status is ever sent bare, and it fills the payload exactly.
        Err(e) => match Response::read(bytes) {
            Ok(r) if r.status != 0 && r.body.is_empty() => Ok(r),
            _ => Err(e),
        },
    }
}

/// Reads `data` every way a foreign peer's payload is read: as a channel message, an RPC
/// request and an RPC answer. A channel message that reads must encode again to bytes that
/// read the same, else this panics. For the fuzz target `zenoh_wire` and the tests' damage
/// sweep, which hold every input to it.
#[doc(hidden)]
pub fn read_any(data: &[u8]) {
    if let Ok(view) = decode_channel(data) {
        let again = encode_channel(view.serialization_type, view.meta.iter(), view.message)
            .expect("what was read fits the layout");
        assert_eq!(decode_channel(&again).as_ref(), Ok(&view));
    }
    let _ = decode_request(data);
    let _ = decode_response(data);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(s: &str) -> Vec<u8> {
        let s: String = s.split_whitespace().collect();
        (0..s.len() / 2)
            .map(|i| u8::from_str_radix(&s[2 * i..2 * i + 2], 16).unwrap())
            .collect()
    }

    fn kv() -> Vec<(String, String)> {
        vec![("k".into(), "v".into())]
    }

    const PATTERN: &str = "aimrt_rpc/%2Faimrt.protocols.example.ExampleService%2FGetFooData";
    const FUNC: &str = "pb:/aimrt.protocols.example.ExampleService/GetFooData";

    #[test]
    fn the_spec_goldens_are_ours_byte_for_byte() {
        // §3.3: channel, meta {k: v}, ExampleEventMsg{msg: "hi"}.
        let channel = ChannelPayload {
            serialization_type: "pb".into(),
            meta: kv(),
            message: vec![0x0a, 0x02, 0x68, 0x69],
        };
        let golden = hex("0e 00 00 00 02 70 62 01 01 00 6b 01 00 76 0a 02 68 69");
        assert_eq!(channel.encode().unwrap(), golden);
        assert_eq!(ChannelPayload::decode(&golden).unwrap(), channel);

        // §3.4: request id 0, meta {k: v}, GetFooDataReq{msg: "hi"}.
        assert_eq!(rpc_pattern(FUNC, ""), PATTERN);
        assert_eq!(PATTERN.len(), 64);
        let request = Request {
            serialization_type: "pb".into(),
            reply_to: PATTERN.into(),
            req_id: [0; 4],
            meta: kv(),
            body: vec![0x0a, 0x02, 0x68, 0x69],
        };
        let golden = hex(
            "53 00 00 00 02 70 62 40 61 69 6d 72 74 5f 72 70 63 2f 25 32 46 61 69 6d 72 74 2e 70 72 6f 74 6f 63 6f
             6c 73 2e 65 78 61 6d 70 6c 65 2e 45 78 61 6d 70 6c 65 53 65 72 76 69 63 65 25 32 46 47 65 74 46 6f 6f
             44 61 74 61 00 00 00 00 01 01 00 6b 01 00 76 0a 02 68 69",
        );
        assert_eq!(golden.len(), 87);
        assert_eq!(encode_request(&request).unwrap(), golden);
        assert_eq!(decode_request(&golden).unwrap(), request);

        let ok = Response {
            serialization_type: "pb".into(),
            req_id: [0; 4],
            status: 0,
            body: vec![0x0a, 0x02, 0x68, 0x69],
        };
        let golden = hex("0f 00 00 00 02 70 62 00 00 00 00 00 00 00 00 0a 02 68 69");
        assert_eq!(encode_response(&ok).unwrap(), golden);
        assert_eq!(decode_response(&golden).unwrap(), ok);
    }

    #[test]
    fn both_forms_of_an_error_answer_are_read_and_the_prefixed_one_is_written() {
        let bare = hex("02 70 62 00 00 00 00 eb 03 00 00");
        let answer = decode_response(&bare).unwrap();
        assert_eq!(answer.status, 1003);
        assert!(answer.body.is_empty());
        let written = encode_response(&answer).unwrap();
        assert_eq!(&written[..4], &[11, 0, 0, 0]);
        assert_eq!(&written[4..], &bare[..]);
        assert_eq!(decode_response(&written).unwrap(), answer);
        // A bare "OK" is not a form AimRT sends: it is refused, not guessed at.
        assert!(decode_response(&hex("02 70 62 00 00 00 00 00 00 00 00")).is_err());
    }

    #[test]
    fn keys_carry_the_limit_domain_after_a_slash() {
        assert_eq!(channel_key("/a/b", "pb:T", ""), "channel/%2Fa%2Fb/pb%3AT");
        assert_eq!(rpc_pattern(FUNC, "room1/A2"), format!("{PATTERN}/room1/A2"));
    }

    #[test]
    fn every_cut_and_every_bad_length_is_an_error_never_a_panic() {
        let request = encode_request(&Request {
            serialization_type: "pb".into(),
            reply_to: PATTERN.into(),
            req_id: [1, 2, 3, 4],
            meta: vec![("key".into(), "value".into())],
            body: b"body".to_vec(),
        })
        .unwrap();
        for cut in 0..request.len() {
            assert!(decode_request(&request[..cut]).is_err(), "cut {cut}");
            assert!(ChannelPayload::decode(&request[..cut]).is_err() || cut >= 4);
            let _ = decode_response(&request[..cut]);
        }
        // A length prefix larger than the payload.
        let mut long = request.clone();
        long[..4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            decode_request(&long),
            Err(PayloadError::LengthBeyondPayload { .. })
        ));
        // Trailing bytes after the prefixed length are ignored.
        let mut trailing = request.clone();
        trailing.extend_from_slice(&[0xde, 0xad, 0xbe, 0xef]);
        assert_eq!(
            decode_request(&trailing).unwrap(),
            decode_request(&request).unwrap()
        );
        // Deterministic garbage of every length up to 300.
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
            let _ = ChannelPayload::decode(&bytes);
            let _ = decode_request(&bytes);
            let _ = decode_response(&bytes);
        }
    }
}
