//! The payloads of AimRT's pub/sub transports (zenoh_plugin and mqtt_plugin lay them out
//! the same way; zenoh puts a `u32_le` length in front of each, mqtt does not):
//!
//! | payload  | fields |
//! |----------|--------|
//! | channel  | `str8` serialization type, meta, message |
//! | request  | `str8` serialization type, `str8` where the answer goes, 4 bytes request id, meta, request |
//! | response | `str8` serialization type, the request's 4 id bytes, `u32_le` status, response |
//!
//! The request id is AimRT's `u32` written little-endian; a server echoes the 4 bytes as
//! they came. "Where the answer goes" is zenoh's RPC pattern or mqtt's response topic.
//!
//! ```
//! use aimrt_wire::payload::{Request, Response};
//! let req = Request {
//!     serialization_type: "pb".into(),
//!     reply_to: "aimrt_rpc_rsp/client/%2FSvc%2FM".into(),
//!     req_id: 7u32.to_le_bytes(),
//!     meta: vec![("k".into(), "v".into())],
//!     body: b"hi".to_vec(),
//! };
//! let mut bytes = Vec::new();
//! req.write_to(&mut bytes).unwrap();
//! assert_eq!(Request::read(&bytes).unwrap(), req);
//!
//! let rsp = Response { serialization_type: "pb".into(), req_id: req.req_id, status: 0, body: b"ok".to_vec() };
//! let mut bytes = Vec::new();
//! rsp.write_to(&mut bytes).unwrap();
//! assert_eq!(Response::read(&bytes).unwrap(), rsp);
//! ```

use aimrt_plugin_api::meta_keys;
use aimrt_plugin_api::rpc::{BackendAnswer, BackendCall};
use aimrt_plugin_api::RpcStatus;

use crate::{meta_len, put_meta, put_str8, MetaBlock, Reader, WireError};

/// A channel payload read in place (the receive path: the message is not copied).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelView<'a> {
    /// `pb`, `json`, …
    pub serialization_type: &'a str,
    /// The meta, in wire order, read in place.
    pub meta: MetaBlock<'a>,
    /// The encoded message.
    pub message: &'a [u8],
}

impl<'a> ChannelView<'a> {
    /// Reads a channel payload: everything after the meta is the message.
    pub fn read(bytes: &'a [u8]) -> Result<ChannelView<'a>, WireError> {
        let mut r = Reader::new(bytes);
        Ok(ChannelView {
            serialization_type: r.str8_ref("serialization type")?,
            meta: r.meta_block()?,
            message: r.rest(),
        })
    }
}

/// Appends a channel payload's fields before its message (the message goes right
/// behind them).
///
/// ```
/// let mut out = Vec::new();
/// aimrt_wire::payload::put_channel_header(&mut out, "pb", [("k", "v")]).unwrap();
/// assert_eq!(out, [2, b'p', b'b', 1, 1, 0, b'k', 1, 0, b'v']);
/// ```
pub fn put_channel_header<K: AsRef<[u8]>, V: AsRef<[u8]>>(
    out: &mut Vec<u8>,
    serialization_type: &str,
    meta: impl IntoIterator<Item = (K, V)>,
) -> Result<(), WireError> {
    put_str8(out, "serialization type", serialization_type)?;
    put_meta(out, meta)
}

/// The bytes [`put_channel_header`] writes.
pub fn channel_header_len<K: AsRef<[u8]>, V: AsRef<[u8]>>(
    serialization_type: &str,
    meta: impl IntoIterator<Item = (K, V)>,
) -> usize {
    1 + serialization_type.len() + meta_len(meta)
}

fn meta_iter(meta: &[(String, String)]) -> impl Iterator<Item = (&String, &String)> + Clone {
    meta.iter().map(|(k, v)| (k, v))
}

/// One RPC request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request {
    /// `pb`, `json`, …
    pub serialization_type: String,
    /// Where the answer goes: zenoh's RPC pattern (the answer key is `rsp/<it>`), or
    /// mqtt's response topic.
    pub reply_to: String,
    /// The request id, echoed raw in the answer.
    pub req_id: [u8; 4],
    /// The context's meta (the timeout is not carried).
    pub meta: Vec<(String, String)>,
    /// The encoded request.
    pub body: Vec<u8>,
}

impl Request {
    /// The bytes [`write_to`](Self::write_to) writes.
    pub fn encoded_len(&self) -> usize {
        6 + self.serialization_type.len()
            + self.reply_to.len()
            + meta_len(meta_iter(&self.meta))
            + self.body.len()
    }

    /// Appends the request.
    pub fn write_to(&self, out: &mut Vec<u8>) -> Result<(), WireError> {
        out.reserve(self.encoded_len());
        put_str8(out, "serialization type", &self.serialization_type)?;
        put_str8(out, "reply key", &self.reply_to)?;
        out.extend_from_slice(&self.req_id);
        put_meta(out, meta_iter(&self.meta))?;
        out.extend_from_slice(&self.body);
        Ok(())
    }

    /// Reads a request: everything after the meta is the body.
    pub fn read(bytes: &[u8]) -> Result<Request, WireError> {
        let mut r = Reader::new(bytes);
        let serialization_type = r.str8("serialization type")?;
        let reply_to = r.str8("reply key")?;
        let id = r.take("request id", 4)?;
        Ok(Request {
            serialization_type,
            reply_to,
            req_id: [id[0], id[1], id[2], id[3]],
            meta: r.meta()?,
            body: r.rest().to_vec(),
        })
    }
}

impl Request {
    /// The call this request makes of `func`, as a server hands it to the runtime (its
    /// serialization type, its meta, AimRT's `aimrt-function_name`), and what its answer
    /// needs.
    ///
    /// ```
    /// use aimrt_plugin_api::rpc::BackendAnswer;
    /// use aimrt_wire::payload::Request;
    /// let req = Request { serialization_type: "pb".into(), reply_to: "r".into(), req_id: [1, 0, 0, 0], meta: vec![], body: b"q".to_vec() };
    /// let (call, answering) = req.into_call("pb:/a.B/C");
    /// assert_eq!(call.meta("aimrt-function_name"), Some("pb:/a.B/C"));
    /// assert_eq!(answering.reply_to, "r");
    /// let rsp = answering.response(BackendAnswer::ok(b"a".to_vec()));
    /// assert_eq!((rsp.status, rsp.req_id, rsp.body), (0, [1, 0, 0, 0], b"a".to_vec()));
    /// ```
    pub fn into_call(self, func: &str) -> (BackendCall, Answering) {
        let mut call = BackendCall::new(func);
        call.set_meta(meta_keys::SERIALIZATION_TYPE, &self.serialization_type);
        for (k, v) in &self.meta {
            call.set_meta(k, v);
        }
        call.set_meta(meta_keys::FUNCTION_NAME, func);
        call.body = self.body;
        let answering = Answering {
            serialization_type: self.serialization_type,
            reply_to: self.reply_to,
            req_id: self.req_id,
        };
        (call, answering)
    }
}

/// What the answer to a request needs: where it goes, and the request's serialization
/// type and id.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Answering {
    /// The request's serialization type.
    pub serialization_type: String,
    /// Where the answer goes.
    pub reply_to: String,
    /// The request's id bytes.
    pub req_id: [u8; 4],
}

impl Answering {
    /// The answer for the runtime's `answer`: its body when OK, else its status alone.
    pub fn response(&self, answer: BackendAnswer) -> Response {
        self.status(answer.status, answer.body)
    }

    /// The answer with `status` (the body only when it is OK).
    pub fn status(&self, status: RpcStatus, body: Vec<u8>) -> Response {
        let ok = status.is_ok();
        Response {
            serialization_type: self.serialization_type.clone(),
            req_id: self.req_id,
            status: if ok { 0 } else { status.code() },
            body: if ok { body } else { Vec::new() },
        }
    }
}

/// One RPC answer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Response {
    /// The request's serialization type.
    pub serialization_type: String,
    /// The request's id bytes.
    pub req_id: [u8; 4],
    /// The AimRT status code (0: OK).
    pub status: u32,
    /// The encoded response (empty unless OK).
    pub body: Vec<u8>,
}

impl Response {
    /// The bytes [`write_to`](Self::write_to) writes.
    pub fn encoded_len(&self) -> usize {
        9 + self.serialization_type.len() + self.body.len()
    }

    /// Appends the answer.
    pub fn write_to(&self, out: &mut Vec<u8>) -> Result<(), WireError> {
        out.reserve(self.encoded_len());
        put_str8(out, "serialization type", &self.serialization_type)?;
        out.extend_from_slice(&self.req_id);
        out.extend_from_slice(&self.status.to_le_bytes());
        out.extend_from_slice(&self.body);
        Ok(())
    }

    /// Reads an answer: everything after the status is the body.
    pub fn read(bytes: &[u8]) -> Result<Response, WireError> {
        let mut r = Reader::new(bytes);
        let serialization_type = r.str8("serialization type")?;
        let id = r.take("request id", 4)?;
        let status = r.u32("status")?;
        Ok(Response {
            serialization_type,
            req_id: [id[0], id[1], id[2], id[3]],
            status,
            body: r.rest().to_vec(),
        })
    }
}
