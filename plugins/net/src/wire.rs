//! AimRT's channel message layout on the wire (net_plugin `tcp` and `udp`): the body
//! `u8 len + uri`, `u8 len + serialization type`, `u8 meta count`, per pair `u16_le len +
//! key`, `u16_le len + value`, then the payload to the end; over TCP a frame is
//! `"YT" + u32_le length + body`. The uri is `/channel/<UrlEncode(topic)>/<UrlEncode(type)>`.

use aimrt_wire::{check_len, put_meta, put_str8, Reader};
pub use aimrt_wire::{url_encode, WireError};

/// The uri of a topic and message type: `/channel/<UrlEncode(topic)>/<UrlEncode(type)>`.
pub fn channel_uri(topic: &str, msg_type: &str) -> String {
    format!("/channel/{}/{}", url_encode(topic), url_encode(msg_type))
}

/// One message as the body lays it out, borrowed from the bytes it was read from (or from
/// the publication it is made of): reading or writing one copies nothing but the meta
/// list.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Body<'a> {
    /// `/channel/<topic>/<type>`, URL-encoded.
    pub uri: &'a str,
    /// `pb`, `json`, …
    pub serialization_type: &'a str,
    /// The context's meta pairs, in wire order.
    pub meta: aimrt_wire::MetaRefs<'a>,
    /// The encoded message.
    pub payload: &'a [u8],
}

impl<'a> Body<'a> {
    /// The bytes of the body; `TooLong` when a field does not fit its prefix (AimRT logs
    /// and drops such a message).
    pub fn encode(&self) -> Result<Vec<u8>, WireError> {
        let mut out = body_header(
            self.uri,
            self.serialization_type,
            || self.meta.iter().copied(),
            self.payload.len(),
        )?;
        out.extend_from_slice(self.payload);
        Ok(out)
    }

    /// Parses a body; every length is checked against what remains.
    pub fn decode(bytes: &'a [u8]) -> Result<Body<'a>, WireError> {
        let mut r = Reader::new(bytes);
        Ok(Body {
            uri: r.str8_ref("uri")?,
            serialization_type: r.str8_ref("serialization type")?,
            meta: r.meta_ref()?,
            payload: r.rest(),
        })
    }
}

/// A body's bytes up to its payload (uri, serialization type, meta), in a buffer with
/// room for `payload` more bytes: the payload is appended behind it.
pub fn body_header<M, K, V>(
    uri: &str,
    serialization_type: &str,
    meta: impl Fn() -> M,
    payload: usize,
) -> Result<Vec<u8>, WireError>
where
    M: Iterator<Item = (K, V)>,
    K: AsRef<[u8]>,
    V: AsRef<[u8]>,
{
    check_len("uri", uri.len(), 255)?;
    let mut out = Vec::with_capacity(
        2 + uri.len() + serialization_type.len() + aimrt_wire::meta_len(meta()) + payload,
    );
    put_str8(&mut out, "uri", uri)?;
    put_str8(&mut out, "serialization type", serialization_type)?;
    put_meta(&mut out, meta())?;
    Ok(out)
}

/// The TCP frame of a body: `"YT"` + `u32_le` length + the body.
pub fn tcp_frame(body: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(6 + body.len());
    out.extend_from_slice(b"YT");
    out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    out.extend_from_slice(body);
    out
}

/// What a TCP byte stream holds, frame by frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Frame {
    /// A body (`length > 0`).
    Body(Vec<u8>),
    /// A heartbeat (`length == 0`): nothing to deliver.
    Heartbeat,
}

/// Reads `data` every way a peer's bytes are read: as one body, and as a tcp stream cut
/// into frames whose bodies are read. Checks that the frames and what is left in the
/// buffer are exactly the stream, and panics when they are not. For the fuzz target
/// `net_wire` and the tests' damage sweep, which hold every input to it.
#[doc(hidden)]
pub fn read_any(data: &[u8]) {
    let _ = Body::decode(data);
    let mut stream = data.to_vec();
    if let Ok(frames) = split_frames(&mut stream, 1 << 16) {
        let mut held = stream.len();
        for frame in &frames {
            held += 6;
            if let Frame::Body(body) = frame {
                held += body.len();
                let _ = Body::decode(body);
            }
        }
        assert_eq!(held, data.len(), "frames and the rest are the stream");
    }
}

/// Splits the complete frames off the front of `buf`; the rest (a partial frame) stays.
/// A frame without the `"YT"` magic or longer than `max` is an error: the connection is
/// not worth reading on.
pub fn split_frames(buf: &mut Vec<u8>, max: usize) -> Result<Vec<Frame>, String> {
    let mut frames = Vec::new();
    let mut at = 0;
    while buf.len() - at >= 6 {
        if &buf[at..at + 2] != b"YT" {
            return Err(format!(
                "a frame starts with {:02x} {:02x}, not \"YT\"",
                buf[at],
                buf[at + 1]
            ));
        }
        let len = u32::from_le_bytes([buf[at + 2], buf[at + 3], buf[at + 4], buf[at + 5]]) as usize;
        if len > max {
            return Err(format!("a frame of {len} bytes is over the limit of {max}"));
        }
        if buf.len() - at - 6 < len {
            break;
        }
        frames.push(if len == 0 {
            Frame::Heartbeat
        } else {
            Frame::Body(buf[at + 6..at + 6 + len].to_vec())
        });
        at += 6 + len;
    }
    buf.drain(..at);
    Ok(frames)
}

/// The largest UDP payload (IPv4: 65 535 − 8 − 20).
pub const MAX_DATAGRAM: usize = 65_507;

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(s: &str) -> Vec<u8> {
        let line = format!("x {}", s.split_whitespace().collect::<String>());
        aimrt_plugin_api::__private::hex_lines(&line).remove(0).1
    }

    /// The golden body of the spec (§2.5): meta `{k: v}`, payload `0a 02 68 69`.
    const GOLDEN: &str = "40 2f 63 68 61 6e 6e 65 6c 2f 74 65 73 74 5f 74 6f 70 69 63 2f 70 62 25 33 41 61 69 6d 72 74 2e
       70 72 6f 74 6f 63 6f 6c 73 2e 65 78 61 6d 70 6c 65 2e 45 78 61 6d 70 6c 65 45 76 65 6e 74 4d 73
       67 02 70 62 01 01 00 6b 01 00 76 0a 02 68 69";

    #[test]
    fn the_spec_golden_body_and_frame_are_ours_byte_for_byte() {
        let uri = channel_uri("test_topic", "pb:aimrt.protocols.example.ExampleEventMsg");
        let body = Body {
            uri: &uri,
            serialization_type: "pb",
            meta: vec![("k", "v")].into(),
            payload: &[0x0a, 0x02, 0x68, 0x69],
        };
        let bytes = body.encode().unwrap();
        assert_eq!(bytes, hex(GOLDEN));
        assert_eq!(bytes.len(), 79);
        let back = Body::decode(&bytes).unwrap();
        assert_eq!(
            (
                back.uri,
                back.serialization_type,
                &back.meta[..],
                back.payload
            ),
            (
                body.uri,
                body.serialization_type,
                &body.meta[..],
                body.payload
            )
        );
        let frame = tcp_frame(&bytes);
        assert_eq!(&frame[..6], &[0x59, 0x54, 0x4f, 0, 0, 0]);
        assert_eq!(frame.len(), 85);
    }

    /// `<label> <hex>` lines of a wire fixture.
    fn fixture(file: &str) -> Vec<(String, Vec<u8>)> {
        let path = format!(
            "{}/../../tests/fixtures/aimrt-wire/{file}",
            env!("CARGO_MANIFEST_DIR")
        );
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
        aimrt_plugin_api::__private::hex_lines(&text)
    }

    const URI: &str = "/channel/test_topic/pb%3Aaimrt.protocols.example.ExampleEventMsg";

    /// A message AimRT's example publisher sent: its uri, `pb` or `json`, and meta that
    /// round-trips.
    fn check_example(label: &str, body: &[u8]) {
        let b = Body::decode(body).unwrap_or_else(|e| panic!("{label}: {e}"));
        assert_eq!(b.uri, URI, "{label}");
        match b.serialization_type {
            "pb" => assert!(!b.payload.is_empty(), "{label}"),
            "json" => assert!(b.payload.starts_with(b"{"), "{label}"),
            other => panic!("{label}: serialization type {other}"),
        }
        // Our encoding of what we decoded is AimRT's bytes (meta in wire order).
        assert_eq!(b.encode().unwrap(), body, "{label}");
    }

    #[test]
    fn every_udp_and_tcp_capture_decodes_as_aimrt_sent_it() {
        for (label, bytes) in fixture("udp_channel_pb.hex")
            .into_iter()
            .chain(fixture("udp_channel_to_sub.hex"))
        {
            match label.as_str() {
                "datagram_1" | "datagram_2" | "replay_of_datagram_1" | "min_pb" => {
                    check_example(&label, &bytes)
                }
                // AimRT's subscriber read 'Y' as the uri length and found no such uri.
                "with_tcp_header" => {
                    let uri = Body::decode(&bytes).map(|b| b.uri);
                    assert!(uri.is_err() || uri.is_ok_and(|u| u != URI), "{label}");
                }
                other => panic!("udp fixture case '{other}' has no test"),
            }
        }
        for (label, bytes) in fixture("tcp_channel_pb.hex")
            .into_iter()
            .chain(fixture("tcp_channel_to_sub.hex"))
        {
            let mut buf = bytes.clone();
            let frames = split_frames(&mut buf, 16 << 20);
            match label.as_str() {
                "frame_1" | "frame_2" | "replay_of_frame_1" | "min_pb" => {
                    let frames = frames.unwrap();
                    assert_eq!(frames.len(), 1, "{label}");
                    assert!(buf.is_empty(), "{label}");
                    let Frame::Body(body) = &frames[0] else {
                        panic!("{label}: a heartbeat")
                    };
                    check_example(&label, body);
                    assert_eq!(tcp_frame(body), bytes, "{label}");
                }
                "heartbeat_then_two_frames" => {
                    let frames = frames.unwrap();
                    assert_eq!(frames.len(), 3, "{label}");
                    assert_eq!(frames[0], Frame::Heartbeat);
                    for f in &frames[1..] {
                        let Frame::Body(body) = f else {
                            panic!("{label}")
                        };
                        check_example(&label, body);
                    }
                }
                "bad_magic" => assert!(frames.is_err(), "{label}"),
                other => panic!("tcp fixture case '{other}' has no test"),
            }
        }
    }

    /// Every udp and tcp capture damaged every way (`__private::damaged`), as a body and as
    /// a tcp stream: an error or what reads, never a panic; frames never hold more than
    /// the stream. The fuzz target `net_wire` does the same with any bytes, outside CI.
    #[test]
    fn every_capture_damaged_anywhere_is_an_error_or_reads() {
        let dir = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../tests/fixtures/aimrt-wire"
        );
        let files = [
            "udp_channel_pb.hex",
            "udp_channel_to_sub.hex",
            "tcp_channel_pb.hex",
            "tcp_channel_to_sub.hex",
        ];
        let tried = aimrt_plugin_api::__private::read_damaged_captures(dir, &files, read_any);
        assert!(tried > 10_000, "{tried} damaged captures");
    }

    #[test]
    fn frames_split_across_reads_come_out_whole() {
        let body = hex(GOLDEN);
        let mut stream = tcp_frame(&[]);
        stream.extend(tcp_frame(&body));
        stream.extend(tcp_frame(&body));
        let mut buf = Vec::new();
        let mut got = Vec::new();
        for chunk in stream.chunks(7) {
            buf.extend_from_slice(chunk);
            got.extend(split_frames(&mut buf, 1 << 20).unwrap());
        }
        assert!(buf.is_empty());
        assert_eq!(
            got,
            [
                Frame::Heartbeat,
                Frame::Body(body.clone()),
                Frame::Body(body)
            ]
        );
        let mut huge = b"YT".to_vec();
        huge.extend_from_slice(&(2u32 << 20).to_le_bytes());
        assert!(split_frames(&mut huge, 1 << 20)
            .unwrap_err()
            .contains("over the limit"));
    }

    #[test]
    fn every_cut_and_every_bad_length_is_an_error_never_a_panic() {
        let bytes = hex(GOLDEN);
        for n in 0..69 {
            // Up to the end of the meta: a cut inside a field.
            assert!(
                matches!(Body::decode(&bytes[..n]), Err(WireError::Truncated { .. })),
                "{n}"
            );
        }
        // A length prefix beyond the end.
        let mut bad = bytes.clone();
        bad[0] = 0xff;
        assert!(Body::decode(&bad).is_err());
        let mut bad = bytes.clone();
        bad[69] = 0xff;
        bad[70] = 0xff;
        assert!(matches!(
            Body::decode(&bad),
            Err(WireError::Truncated { .. })
        ));
        // Not UTF-8.
        let mut bad = bytes.clone();
        bad[1] = 0xff;
        assert_eq!(Body::decode(&bad), Err(WireError::NotUtf8("uri")));
        // Random bytes: an answer, whatever they are.
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        for len in 0..2000 {
            let junk: Vec<u8> = (0..len % 300)
                .map(|_| {
                    seed ^= seed << 13;
                    seed ^= seed >> 7;
                    seed ^= seed << 17;
                    seed as u8
                })
                .collect();
            let _ = Body::decode(&junk);
        }
        // Too long to encode.
        let keys: Vec<String> = (0..256).map(|i| i.to_string()).collect();
        let too_many = Body {
            uri: "/channel/a/b",
            serialization_type: "pb",
            meta: keys.iter().map(|k| (k.as_str(), "")).collect(),
            payload: &[],
        };
        assert!(matches!(too_many.encode(), Err(WireError::TooLong { .. })));
    }
}
