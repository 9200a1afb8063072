//! The context of one RPC call: its side, timeout and meta key/values, as AimRT's
//! `aimrt::rpc::Context`.

use crate::meta::Meta;
use std::time::Duration;

/// The meta keys the framework reads and writes (AimRT's names).
pub mod meta_keys {
    /// Where a client call goes, e.g. `http://127.0.0.1:50080` (backend specific).
    pub const TO_ADDR: &str = "aimrt-to_addr";
    /// The serialization of request and response: `pb` or `json`.
    pub const SERIALIZATION_TYPE: &str = "aimrt-serialization_type";
    /// The full function name, written by every client before it invokes.
    pub const FUNCTION_NAME: &str = "aimrt-function_name";
    /// The backend that carried the call.
    pub const BACKEND: &str = "aimrt-backend";
    /// A request's id on backends that number requests.
    pub const REQUEST_ID: &str = "aimrt-request_id";
    /// The id of the request a response answers.
    pub const RESPONSE_ID: &str = "aimrt-response_id";
    /// The pkg of the calling module (`local` backend, server side).
    pub const FROM_PKG: &str = "aimrt-from_pkg";
    /// The calling module (`local` backend, server side).
    pub const FROM_MODULE: &str = "aimrt-from_module";
}

/// Which side of a call a context belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RpcContextKind {
    /// Made by a client for one call.
    Client,
    /// Handed to a service with a request.
    Server,
}

/// One call's context: a timeout (none by default), meta key/values in the order they
/// were first set, and whether a call has used it. A client context serves one call:
/// a used one is refused with [`RpcStatus::CLI_INVALID_CONTEXT`](crate::RpcStatus) until
/// [`reset`](Self::reset). A clone copies side, timeout and meta, not the used mark.
///
/// ```
/// use std::time::Duration;
/// use aimrt_plugin_api::{RpcContext, RpcContextKind};
///
/// let mut ctx = RpcContext::client();
/// ctx.set_timeout(Some(Duration::from_secs(3)));
/// ctx.set_meta("aimrt-request_id", "1");
/// ctx.set_meta("k", "v");
/// assert_eq!(ctx.meta("k"), Some("v"));
/// assert_eq!(
///     ctx.to_string(),
///     r#"Client context, timeout: 3000ms, meta: {{"aimrt-request_id":"1"},{"k":"v"}}"#
/// );
/// ctx.set_used();
/// let copy = ctx.clone();
/// assert!(ctx.is_used() && !copy.is_used());
/// assert_eq!(copy.kind(), RpcContextKind::Client);
/// ```
#[derive(Debug)]
pub struct RpcContext {
    kind: RpcContextKind,
    timeout: Option<Duration>,
    meta: Meta,
    used: bool,
}

impl RpcContext {
    /// An empty, unused context of `kind`.
    pub fn new(kind: RpcContextKind) -> RpcContext {
        RpcContext {
            kind,
            timeout: None,
            meta: Meta::default(),
            used: false,
        }
    }

    /// An empty client context.
    pub fn client() -> RpcContext {
        RpcContext::new(RpcContextKind::Client)
    }

    /// An empty server context.
    pub fn server() -> RpcContext {
        RpcContext::new(RpcContextKind::Server)
    }

    /// The side this context belongs to.
    pub fn kind(&self) -> RpcContextKind {
        self.kind
    }

    /// The call's timeout; `None` leaves it to the backend (AimRT's 0).
    pub fn timeout(&self) -> Option<Duration> {
        self.timeout
    }

    /// Sets the timeout; `None` or zero unsets it (AimRT: 0 ns means unset).
    pub fn set_timeout(&mut self, timeout: Option<Duration>) {
        self.timeout = timeout.filter(|t| !t.is_zero());
    }

    /// The value of meta `key`, if set.
    pub fn meta(&self, key: &str) -> Option<&str> {
        self.meta.get(key)
    }

    /// Sets meta `key` to `value` (replacing an earlier value in its place).
    pub fn set_meta(&mut self, key: &str, value: &str) {
        self.meta.set(key, value);
    }

    /// A context of `kind` with `timeout` and `pairs` (a context copied from the ABI,
    /// whose keys are distinct): one UTF-8 check of its text, a part that is not UTF-8
    /// read as empty.
    pub(crate) fn from_distinct(
        kind: RpcContextKind,
        timeout: Option<Duration>,
        pairs: &[crate::ffi::MetaPair<'_>],
    ) -> RpcContext {
        RpcContext {
            kind,
            timeout: timeout.filter(|t| !t.is_zero()),
            meta: Meta::from_abi(pairs),
            used: false,
        }
    }

    /// Every meta key/value, in the order the keys were first set.
    pub fn meta_pairs(&self) -> impl Iterator<Item = (&str, &str)> {
        self.meta.iter()
    }

    /// `aimrt-serialization_type`, if set (the backend's default otherwise, `pb`).
    pub fn serialization_type(&self) -> Option<&str> {
        self.meta(meta_keys::SERIALIZATION_TYPE)
    }

    /// Sets `aimrt-serialization_type` (`pb` or `json`).
    pub fn set_serialization_type(&mut self, ty: &str) {
        self.set_meta(meta_keys::SERIALIZATION_TYPE, ty);
    }

    /// `aimrt-to_addr`, if set.
    pub fn to_addr(&self) -> Option<&str> {
        self.meta(meta_keys::TO_ADDR)
    }

    /// Sets `aimrt-to_addr`: where a client call goes (backend specific).
    pub fn set_to_addr(&mut self, addr: &str) {
        self.set_meta(meta_keys::TO_ADDR, addr);
    }

    /// Whether a call has used this context.
    pub fn is_used(&self) -> bool {
        self.used
    }

    /// Marks the context used (a client does this when it invokes).
    pub fn set_used(&mut self) {
        self.used = true;
    }

    /// Clears the used mark, the timeout and the meta (AimRT's `Reset`).
    pub fn reset(&mut self) {
        self.used = false;
        self.timeout = None;
        self.meta.clear();
    }

    /// Copies into this client context the non-empty values of `passed_keys` from the
    /// server context `server` (AimRT's `MergeServerContextToClientContext`; the keys
    /// are those plugins register to pass along a chain of calls, e.g. trace ids).
    /// Does nothing unless `self` is a client context and `server` a server context.
    ///
    /// ```
    /// use aimrt_plugin_api::RpcContext;
    /// let mut server = RpcContext::server();
    /// server.set_meta("trace", "abc");
    /// server.set_meta("other", "x");
    /// server.set_meta("empty", "");
    /// let mut client = RpcContext::client();
    /// client.merge_from_server(&server, &["trace", "empty"]);
    /// assert_eq!(client.meta("trace"), Some("abc"));
    /// assert_eq!(client.meta("other"), None);
    /// assert_eq!(client.meta("empty"), None);
    /// ```
    pub fn merge_from_server(&mut self, server: &RpcContext, passed_keys: &[&str]) {
        if self.kind != RpcContextKind::Client || server.kind != RpcContextKind::Server {
            return;
        }
        for key in passed_keys {
            if let Some(value) = server.meta(key).filter(|v| !v.is_empty()) {
                self.set_meta(key, value);
            }
        }
    }
}

impl Default for RpcContext {
    /// A client context, as AimRT's default.
    fn default() -> Self {
        RpcContext::client()
    }
}

/// Copies side, timeout and meta; the copy is unused (AimRT's copy constructor).
impl Clone for RpcContext {
    fn clone(&self) -> Self {
        RpcContext {
            kind: self.kind,
            timeout: self.timeout,
            meta: self.meta.clone(),
            used: false,
        }
    }
}

/// AimRT's `ToString()`: `Client context, timeout: 3000ms, meta: {{"k":"v"}}`.
impl std::fmt::Display for RpcContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let side = match self.kind {
            RpcContextKind::Client => "Client",
            RpcContextKind::Server => "Server",
        };
        let ms = self.timeout.map_or(0, |t| t.as_millis());
        write!(f, "{side} context, timeout: {ms}ms, meta: {{")?;
        for (i, (k, v)) in self.meta.iter().enumerate() {
            if i > 0 {
                f.write_str(",")?;
            }
            write!(f, "{{\"{k}\":\"{v}\"}}")?;
        }
        f.write_str("}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reset_clears_everything_and_set_meta_replaces_in_place() {
        let mut c = RpcContext::client();
        c.set_meta("a", "1");
        c.set_meta("b", "2");
        c.set_meta("a", "3");
        assert_eq!(c.meta_pairs().collect::<Vec<_>>(), [("a", "3"), ("b", "2")]);
        c.set_timeout(Some(Duration::from_millis(5)));
        c.set_used();
        c.reset();
        assert!(!c.is_used());
        assert_eq!(c.timeout(), None);
        assert_eq!(c.meta_pairs().count(), 0);
        assert_eq!(c.to_string(), "Client context, timeout: 0ms, meta: {}");
    }

    #[test]
    fn zero_timeout_is_unset_and_framework_keys_have_aimrts_names() {
        let mut c = RpcContext::server();
        c.set_timeout(Some(Duration::ZERO));
        assert_eq!(c.timeout(), None);
        c.set_serialization_type("json");
        c.set_to_addr("http://127.0.0.1:50080");
        assert_eq!(c.meta("aimrt-serialization_type"), Some("json"));
        assert_eq!(c.meta("aimrt-to_addr"), Some("http://127.0.0.1:50080"));
        assert!(c.to_string().starts_with(
            "Server context, timeout: 0ms, meta: {{\"aimrt-serialization_type\":\"json\"}"
        ));
    }

    #[test]
    fn merge_needs_a_client_and_a_server_context() {
        let mut server = RpcContext::server();
        server.set_meta("trace", "abc");
        let mut other_client = RpcContext::client();
        other_client.set_meta("trace", "abc");
        let mut client = RpcContext::client();
        client.merge_from_server(&other_client, &["trace"]);
        assert_eq!(client.meta("trace"), None);
        let mut as_server = RpcContext::server();
        as_server.merge_from_server(&server, &["trace"]);
        assert_eq!(as_server.meta("trace"), None);
        client.merge_from_server(&server, &["trace"]);
        assert_eq!(client.meta("trace"), Some("abc"));
    }
}
