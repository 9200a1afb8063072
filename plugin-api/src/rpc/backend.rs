//! Module calls as an RPC backend sees them: bytes in a named format, meta key/values, a
//! timeout, and an answer with an AimRT status code. The same shapes carry a client call
//! from the runtime to a backend ([`RpcBackend::invoke`](super::RpcBackend::invoke)) and a
//! call a backend received to the runtime ([`ServiceHost::call`](super::ServiceHost::call)).

use std::time::Duration;

use super::context::meta_keys;
use super::RpcStatus;
use crate::ffi::{MetaPair, RawBackendReply};
use crate::meta::Meta;

/// One call crossing between the runtime and a backend. Its meta (the context's
/// key/values, `aimrt-serialization_type` included) lives in one buffer: a call costs a
/// few allocations however many keys it carries.
///
/// ```
/// # use aimrt_plugin_api::rpc::BackendCall;
/// let mut call = BackendCall::new("pb:/example.Service/Get");
/// call.set_meta("aimrt-serialization_type", "pb");
/// call.set_meta("k", "v1");
/// call.set_meta("k", "v2");
/// assert_eq!(call.meta("k"), Some("v2"));
/// assert_eq!(call.meta_pairs().collect::<Vec<_>>(), [("aimrt-serialization_type", "pb"), ("k", "v2")]);
/// ```
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BackendCall {
    /// The full function name (`pb:/aimrt.protocols.example.ExampleService/GetFooData`).
    pub func: String,
    meta: Meta,
    /// The time left for the answer; `None` when the caller gave none.
    pub timeout: Option<Duration>,
    /// The request, encoded in the serialization type.
    pub body: Vec<u8>,
}

impl BackendCall {
    /// A call of `func` with no meta, no timeout and an empty body.
    pub fn new(func: impl Into<String>) -> BackendCall {
        BackendCall {
            func: func.into(),
            ..BackendCall::default()
        }
    }

    /// A call whose meta pairs are `pairs`, whose keys are known to be distinct (what
    /// crossed the ABI).
    pub(crate) fn from_abi(
        func: String,
        pairs: &[MetaPair<'_>],
        timeout: Option<Duration>,
        body: Vec<u8>,
    ) -> BackendCall {
        BackendCall {
            func,
            meta: Meta::from_abi(pairs),
            timeout,
            body,
        }
    }

    /// The value of a meta key.
    pub fn meta(&self, key: &str) -> Option<&str> {
        self.meta.get(key)
    }

    /// Sets a meta key (replacing its value).
    pub fn set_meta(&mut self, key: &str, value: &str) {
        self.meta.set(key, value);
    }

    /// Every meta pair, in the order the keys were first set.
    pub fn meta_pairs(&self) -> impl Iterator<Item = (&str, &str)> {
        self.meta.iter()
    }

    /// How many meta pairs the call has.
    pub fn meta_len(&self) -> usize {
        self.meta.len()
    }

    /// `aimrt-serialization_type`, if set.
    pub fn serialization_type(&self) -> Option<&str> {
        self.meta(meta_keys::SERIALIZATION_TYPE)
    }
}

/// A call a backend received, borrowed for the duration of
/// [`HostServices::call_view`](super::HostServices::call_view): what crosses the ABI,
/// read in place.
#[derive(Debug, Clone, Copy)]
pub struct CallView<'a> {
    /// The full function name.
    pub func: &'a str,
    pub(crate) meta: &'a [MetaPair<'a>],
    /// The time left for the answer; `None` when the caller gave none.
    pub timeout: Option<Duration>,
    /// The request, encoded in the serialization type.
    pub body: &'a [u8],
}

impl<'a> CallView<'a> {
    /// A view of a call of `func` with `meta` (distinct keys).
    pub fn new(
        func: &'a str,
        meta: &'a [MetaPair<'a>],
        timeout: Option<Duration>,
        body: &'a [u8],
    ) -> CallView<'a> {
        CallView {
            func,
            meta,
            timeout,
            body,
        }
    }

    /// Every meta pair, in order (a key or value that is not UTF-8 reads as empty).
    pub fn meta_pairs(&self) -> impl Iterator<Item = (&'a str, &'a str)> + 'a {
        self.meta.iter().map(|p| (p.key(), p.value()))
    }

    /// The value of a meta key.
    pub fn meta(&self, key: &str) -> Option<&'a str> {
        self.meta.iter().find(|p| p.is_key(key)).map(|p| p.value())
    }

    /// The meta pairs as they crossed the ABI.
    pub fn pairs(&self) -> &'a [MetaPair<'a>] {
        self.meta
    }

    /// How many meta pairs there are.
    pub fn meta_len(&self) -> usize {
        self.meta.len()
    }

    /// `aimrt-serialization_type`, if set.
    pub fn serialization_type(&self) -> Option<&'a str> {
        self.meta(meta_keys::SERIALIZATION_TYPE)
    }

    /// An owned copy.
    pub fn to_call(&self) -> BackendCall {
        BackendCall::from_abi(
            self.func.to_owned(),
            self.meta,
            self.timeout,
            self.body.to_vec(),
        )
    }
}

/// The answer to one [`BackendCall`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BackendAnswer {
    /// The status (0: the body is the response).
    pub status: RpcStatus,
    /// The response, encoded in the call's serialization type (empty unless OK).
    pub body: Vec<u8>,
    /// Meta to hand back to the caller.
    pub meta: Vec<(String, String)>,
    /// Why the call failed, or empty.
    pub detail: String,
}

impl BackendAnswer {
    /// A successful answer with `body`.
    pub fn ok(body: Vec<u8>) -> BackendAnswer {
        BackendAnswer {
            status: RpcStatus::OK,
            body,
            meta: Vec::new(),
            detail: String::new(),
        }
    }

    /// A failed answer.
    pub fn fail(status: RpcStatus, detail: impl Into<String>) -> BackendAnswer {
        BackendAnswer {
            status,
            body: Vec::new(),
            meta: Vec::new(),
            detail: detail.into(),
        }
    }
}

/// The answer a backend owes one client call, given once with [`send`](Self::send), from
/// any thread. Dropped unanswered, it answers
/// [`RpcStatus::CLI_BACKEND_INTERNAL_ERROR`].
pub struct BackendReply {
    raw: Option<RawBackendReply>,
}

impl std::fmt::Debug for BackendReply {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("BackendReply")
    }
}

impl BackendReply {
    pub(crate) fn new(raw: RawBackendReply) -> BackendReply {
        BackendReply { raw: Some(raw) }
    }

    /// A reply that calls `done` (for backends' own tests).
    pub fn from_fn(done: impl FnOnce(BackendAnswer) + Send + 'static) -> BackendReply {
        BackendReply::new(RawBackendReply::new(done))
    }

    /// Answers the call.
    pub fn send(mut self, answer: BackendAnswer) {
        if let Some(raw) = self.raw.take() {
            raw.complete(&answer);
        }
    }
}

impl Drop for BackendReply {
    fn drop(&mut self) {
        if let Some(raw) = self.raw.take() {
            raw.complete(&BackendAnswer::fail(
                RpcStatus::CLI_BACKEND_INTERNAL_ERROR,
                "the backend dropped the call without an answer",
            ));
        }
    }
}
