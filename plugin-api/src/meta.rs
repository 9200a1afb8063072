//! Key/value meta in one text buffer with the ranges of its pairs: what a channel
//! [`Context`](crate::channel::Context) and an [`RpcContext`](crate::RpcContext) hold.
//! Copying one costs one allocation however many keys it has (the ranges of up to 8
//! pairs live inline), and building one from a context that crossed the ABI checks its
//! text as UTF-8 once.
//!
//! A subscriber's context reads the pairs the ABI lends for the call in place
//! ([`LentPairs`]): nothing is copied unless the context is changed or cloned, which
//! copies the pairs first ([`Meta::from_abi`]).

use crate::ffi::pubsub::LentPairs;
use crate::ffi::MetaPair;

/// The first allocation of a context's text, in bytes.
const FIRST_TEXT: usize = 256;

/// `(key start, key end, value start, value end)` in the text, of up to 8 pairs inline.
type Ranges = smallvec::SmallVec<[(u32, u32, u32, u32); 8]>;

/// Below this many bytes of text, replaced values are not reclaimed.
const COMPACT_AFTER: usize = 4096;

/// Meta key/values, in the order the keys were first set.
#[derive(Debug, Default)]
pub(crate) struct Meta {
    text: String,
    /// `(key start, key end, value start, value end)` in `text`.
    pairs: Ranges,
    /// Pairs read in place; when set, `text` and `pairs` are empty.
    lent: Option<LentPairs>,
}

impl Clone for Meta {
    /// A copy that owns its pairs (a lent context's are copied).
    fn clone(&self) -> Meta {
        match &self.lent {
            Some(lent) => Meta::from_abi(lent.pairs()),
            None => Meta {
                text: self.text.clone(),
                pairs: self.pairs.clone(),
                lent: None,
            },
        }
    }
}

impl PartialEq for Meta {
    fn eq(&self, other: &Meta) -> bool {
        self.iter().eq(other.iter())
    }
}

impl Eq for Meta {}

impl Meta {
    /// The pairs of a context handed over by the ABI, whose keys are known to be
    /// distinct: no search per key, and the text is checked as UTF-8 once. A key or value
    /// that is not UTF-8 reads as empty.
    pub(crate) fn from_abi(pairs: &[MetaPair<'_>]) -> Meta {
        let len: usize = pairs
            .iter()
            .map(|p| {
                let (k, v) = p.bytes();
                k.len() + v.len()
            })
            .sum();
        let mut text = Vec::with_capacity(FIRST_TEXT.max(len));
        let mut ranges = Ranges::with_capacity(pairs.len());
        let mut push = |b: &[u8]| {
            let start = text.len() as u32;
            text.extend_from_slice(b);
            (start, text.len() as u32)
        };
        for p in pairs {
            let (k, v) = p.bytes();
            let (ks, ke) = push(k);
            let (vs, ve) = push(v);
            ranges.push((ks, ke, vs, ve));
        }
        match String::from_utf8(text) {
            // A range that is not UTF-8 on its own (cut inside a character) reads as
            // empty, as `slice` does.
            Ok(text) => Meta {
                text,
                pairs: ranges,
                lent: None,
            },
            Err(_) => {
                let mut meta = Meta::default();
                for p in pairs {
                    meta.push(p.key(), p.value());
                }
                meta
            }
        }
    }

    /// The pairs lent for one call, read in place (distinct keys). A key or value that
    /// is not UTF-8 reads as empty, as in [`from_abi`](Meta::from_abi).
    pub(crate) fn lent(pairs: LentPairs) -> Meta {
        Meta {
            lent: Some(pairs),
            ..Meta::default()
        }
    }

    /// Copies lent pairs in, before a change.
    fn own(&mut self) {
        if let Some(lent) = self.lent.take() {
            *self = Meta::from_abi(lent.pairs());
        }
    }

    /// Whether it reads lent pairs.
    #[cfg(test)]
    pub(crate) fn is_lent(&self) -> bool {
        self.lent.is_some()
    }

    fn lent_pairs(&self) -> &[MetaPair<'_>] {
        self.lent.as_ref().map_or(&[], |l| l.pairs())
    }

    fn push_text(&mut self, s: &str) -> (u32, u32) {
        if self.text.capacity() == 0 {
            // A context gets the framework's keys (aimrt-function_name, …): room for
            // them at once instead of a run of doublings.
            self.text.reserve(FIRST_TEXT.max(s.len()));
        }
        let start = self.text.len();
        self.text.push_str(s);
        // Contexts are small; a text over 4 GiB is not one.
        (start as u32, self.text.len() as u32)
    }

    fn slice(&self, start: u32, end: u32) -> &str {
        self.text.get(start as usize..end as usize).unwrap_or("")
    }

    /// Every pair, in the order the keys were first set.
    pub(crate) fn iter(&self) -> impl Iterator<Item = (&str, &str)> {
        self.iter_unless(|_| false)
    }

    /// The pairs whose key `skip` does not take, in order; keys are shown to `skip` as
    /// bytes, so a lent pair it skips is never checked as UTF-8.
    pub(crate) fn iter_unless<'s>(
        &'s self,
        skip: impl Fn(&[u8]) -> bool + Copy + 's,
    ) -> impl Iterator<Item = (&'s str, &'s str)> + 's {
        let lent = self
            .lent_pairs()
            .iter()
            .filter(move |p| !skip(p.bytes().0))
            .map(|p| (p.key(), p.value()));
        let text = self.text.as_bytes();
        let own = self
            .pairs
            .iter()
            .filter(move |&&(ks, ke, _, _)| {
                !skip(text.get(ks as usize..ke as usize).unwrap_or_default())
            })
            .map(|&(ks, ke, vs, ve)| (self.slice(ks, ke), self.slice(vs, ve)));
        lent.chain(own)
    }

    /// How many pairs there are.
    pub(crate) fn len(&self) -> usize {
        self.pairs.len() + self.lent_pairs().len()
    }

    pub(crate) fn get(&self, key: &str) -> Option<&str> {
        if self.lent.is_some() {
            return self
                .lent_pairs()
                .iter()
                .find(|p| p.is_key(key))
                .map(|p| p.value());
        }
        let i = self.position(key)?;
        let (_, _, vs, ve) = self.pairs[i];
        Some(self.slice(vs, ve))
    }

    /// Where `key` is, compared as bytes (no character boundary checks per pair).
    fn position(&self, key: &str) -> Option<usize> {
        let text = self.text.as_bytes();
        self.pairs
            .iter()
            .position(|&(ks, ke, _, _)| text.get(ks as usize..ke as usize) == Some(key.as_bytes()))
    }

    /// Sets `key` (in place when it is there, else last).
    pub(crate) fn set(&mut self, key: &str, value: &str) {
        self.own();
        match self.position(key) {
            Some(i) => {
                let (vs, ve) = self.push_text(value);
                self.pairs[i].2 = vs;
                self.pairs[i].3 = ve;
                self.compact();
            }
            None => self.push(key, value),
        }
    }

    /// Adds a pair whose key is known not to be there.
    pub(crate) fn push(&mut self, key: &str, value: &str) {
        self.own();
        let (ks, ke) = self.push_text(key);
        let (vs, ve) = self.push_text(value);
        self.pairs.push((ks, ke, vs, ve));
    }

    /// Removes `key`; returns its value.
    pub(crate) fn remove(&mut self, key: &str) -> Option<String> {
        self.own();
        let i = self.position(key)?;
        let (_, _, vs, ve) = self.pairs.remove(i);
        let value = self.slice(vs, ve).to_owned();
        self.compact();
        Some(value)
    }

    /// Drops the text of replaced and removed pairs once it outweighs the live text, so a
    /// context reused with ever new values stays bounded.
    fn compact(&mut self) {
        if self.text.len() <= COMPACT_AFTER {
            return;
        }
        let live: usize = self
            .pairs
            .iter()
            .map(|&(ks, ke, vs, ve)| (ke - ks + ve - vs) as usize)
            .sum();
        if self.text.len() <= 2 * live {
            return;
        }
        let mut fresh = Meta {
            text: String::with_capacity(FIRST_TEXT.max(live)),
            pairs: Ranges::with_capacity(self.pairs.len()),
            lent: None,
        };
        for (k, v) in self.iter() {
            fresh.push(k, v);
        }
        *self = fresh;
    }

    pub(crate) fn clear(&mut self) {
        self.lent = None;
        self.text.clear();
        self.pairs.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_keep_their_order_and_replaced_text_is_reclaimed() {
        let mut m = Meta::default();
        m.set("a", "1");
        m.set("b", "2");
        m.set("a", "3");
        assert_eq!(m.iter().collect::<Vec<_>>(), [("a", "3"), ("b", "2")]);
        assert_eq!(m.remove("a").as_deref(), Some("3"));
        assert_eq!(m.iter().collect::<Vec<_>>(), [("b", "2")]);
        // A context reused with a new value each time stays bounded.
        for i in 0..100_000 {
            m.set("trace", &format!("{i:08}"));
        }
        assert_eq!(m.get("trace"), Some("00099999"));
        assert_eq!(m.get("b"), Some("2"));
        assert!(m.text.len() <= 2 * COMPACT_AFTER, "{}", m.text.len());
        let mut other = Meta::default();
        other.push("b", "2");
        other.push("trace", "00099999");
        assert_eq!(m, other);
    }

    #[test]
    fn a_context_from_the_abi_reads_what_is_not_utf8_as_empty() {
        let read = |pairs: &[MetaPair<'_>]| {
            Meta::from_abi(pairs)
                .iter()
                .map(|(k, v)| (k.to_owned(), v.to_owned()))
                .collect::<Vec<_>>()
        };
        let own = |list: &[(&str, &str)]| {
            list.iter()
                .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
                .collect::<Vec<_>>()
        };
        let valid = [MetaPair::new("aimrt-x", "é1"), MetaPair::new("k", "")];
        assert_eq!(read(&valid), own(&[("aimrt-x", "é1"), ("k", "")]));
        // One bad value: the rest survive.
        let bad = [
            MetaPair::from_bytes(b"a", b"\xff\xfe"),
            MetaPair::from_bytes(b"b", b"2"),
        ];
        assert_eq!(read(&bad), own(&[("a", ""), ("b", "2")]));
        // A character split between a key and its value: valid as a whole, neither part
        // is.
        let split = [
            MetaPair::from_bytes(b"\xc3", b"\xa9"),
            MetaPair::new("c", "3"),
        ];
        assert_eq!(read(&split), own(&[("", ""), ("c", "3")]));
    }
}
