//! The per-message context of a channel: key/value meta and AimRT's `aimrt-*` keys.

use std::fmt;

use crate::meta::Meta;

/// `aimrt-serialization_type`: the format a message travels in (`json`, `postcard`, `pb`).
pub const KEY_SERIALIZATION_TYPE: &str = "aimrt-serialization_type";
/// `aimrt-backend`: the backend that delivered a message (subscribe side).
pub const KEY_BACKEND: &str = "aimrt-backend";
/// `aimrt-to_addr`: where network backends send a message (user set).
pub const KEY_TO_ADDR: &str = "aimrt-to_addr";
/// `aimrt-pub_seq`: the topic's publish counter, from 1 (set by the runtime).
pub const KEY_PUB_SEQ: &str = "aimrt-pub_seq";
/// `aimrt-pub_ts`: the publish time in ns since the epoch (set by the runtime).
pub const KEY_PUB_TS: &str = "aimrt-pub_ts";

/// Which side a context belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ContextKind {
    /// Handed to `publish`; single use.
    Publish,
    /// Handed to a subscriber with the message.
    Subscribe,
}

/// Key/value meta travelling with one message (AimRT's `aimrt::channel::Context`).
///
/// A publish context is single use: publishing marks it used, and publishing it again is
/// refused until [`reset`](Context::reset). Keys starting with `aimrt-` are the runtime's.
///
/// ```
/// use aimrt_plugin_api::channel::{Context, ContextKind, KEY_SERIALIZATION_TYPE};
/// let mut ctx = Context::new(ContextKind::Publish);
/// ctx.set("trace_id", "42");
/// ctx.set(KEY_SERIALIZATION_TYPE, "json");
/// assert_eq!(ctx.get("trace_id"), Some("42"));
/// assert_eq!(ctx.serialization_type(), Some("json"));
/// assert_eq!(
///     ctx.to_string(),
///     r#"Publisher context, meta: {{"trace_id":"42"},{"aimrt-serialization_type":"json"}}"#
/// );
/// ```
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Context {
    kind: ContextKind,
    meta: Meta,
    used: bool,
}

impl Context {
    /// An empty, unused context.
    pub fn new(kind: ContextKind) -> Context {
        Context {
            kind,
            meta: Meta::default(),
            used: false,
        }
    }

    /// Which side it belongs to.
    pub fn kind(&self) -> ContextKind {
        self.kind
    }

    /// The value of `key`.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.meta.get(key)
    }

    /// Sets `key` to `value` (replacing an earlier value; the key keeps its place).
    pub fn set(&mut self, key: &str, value: &str) {
        self.meta.set(key, value);
    }

    /// Removes `key`; returns its value.
    pub fn remove(&mut self, key: &str) -> Option<String> {
        self.meta.remove(key)
    }

    /// Every key/value pair, in the order the keys were first set.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &str)> {
        self.meta.iter()
    }

    /// A context of pairs lent by the ABI for one call (distinct keys), read in place.
    pub(crate) fn lent(kind: ContextKind, pairs: crate::ffi::pubsub::LentPairs) -> Context {
        Context {
            kind,
            meta: Meta::lent(pairs),
            used: false,
        }
    }

    /// `aimrt-serialization_type`, if set.
    pub fn serialization_type(&self) -> Option<&str> {
        self.get(KEY_SERIALIZATION_TYPE)
    }

    /// Sets `aimrt-serialization_type`: the format to publish in (one the message type
    /// supports).
    pub fn set_serialization_type(&mut self, format: &str) {
        self.set(KEY_SERIALIZATION_TYPE, format);
    }

    /// Whether it was published already.
    pub fn is_used(&self) -> bool {
        self.used
    }

    /// Marks it published; publishing it again is refused until [`reset`](Context::reset).
    /// The publisher calls this.
    pub fn mark_used(&mut self) {
        self.used = true;
    }

    /// Makes it reusable: not used, no meta (AimRT's `Reset`).
    pub fn reset(&mut self) {
        self.used = false;
        self.meta.clear();
    }

    /// Copies the user keys of a subscribe context into this publish context, for a
    /// subscriber that publishes what it received (a chain). Keys starting with `aimrt-`
    /// are not copied: the publishing topic sets its own `aimrt-pub_seq`/`aimrt-pub_ts`,
    /// and the format and backend belong to each hop.
    pub fn merge_from(&mut self, received: &Context) {
        for (k, v) in received.meta.iter_unless(|key| key.starts_with(b"aimrt-")) {
            self.set(k, v);
        }
    }
}

impl fmt::Display for Context {
    /// AimRT's layout: `Publisher context, meta: {{"k":"v"},{"k2":"v2"}}`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let side = match self.kind {
            ContextKind::Publish => "Publisher",
            ContextKind::Subscribe => "Subscriber",
        };
        write!(f, "{side} context, meta: {{")?;
        for (i, (k, v)) in self.meta.iter().enumerate() {
            if i > 0 {
                f.write_str(",")?;
            }
            write!(f, "{{{k:?}:{v:?}}}")?;
        }
        f.write_str("}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_replaces_in_place_and_reset_clears() {
        let mut c = Context::new(ContextKind::Publish);
        c.set("a", "1");
        c.set("b", "2");
        c.set("a", "3");
        assert_eq!(c.iter().collect::<Vec<_>>(), [("a", "3"), ("b", "2")]);
        c.mark_used();
        assert!(c.is_used());
        assert_eq!(c.remove("a").as_deref(), Some("3"));
        c.reset();
        assert!(!c.is_used());
        assert_eq!(c.iter().count(), 0);
        assert_eq!(c.to_string(), "Publisher context, meta: {}");
    }

    #[test]
    fn merge_copies_user_keys_only() {
        let mut received = Context::new(ContextKind::Subscribe);
        received.set("trace_id", "7");
        received.set(KEY_PUB_SEQ, "99");
        received.set(KEY_PUB_TS, "123");
        received.set(KEY_BACKEND, "local");
        received.set(KEY_SERIALIZATION_TYPE, "json");
        let mut out = Context::new(ContextKind::Publish);
        out.set("trace_id", "old");
        out.merge_from(&received);
        assert_eq!(out.iter().collect::<Vec<_>>(), [("trace_id", "7")]);
        assert_eq!(
            received.to_string(),
            r#"Subscriber context, meta: {{"trace_id":"7"},{"aimrt-pub_seq":"99"},{"aimrt-pub_ts":"123"},{"aimrt-backend":"local"},{"aimrt-serialization_type":"json"}}"#
        );
    }
}
