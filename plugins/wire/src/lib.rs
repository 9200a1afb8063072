//! AimRT's encodings that net_plugin, zenoh_plugin and mqtt_plugin share, in one place: `UrlEncode` of
//! topics, types and function names, the function name without its prefix, and the field
//! codec of their payloads: `str8` (`u8` length + bytes), `str16` (`u16_le` length +
//! bytes), and the meta block (`u8` pair count, then `str16` key and `str16` value per
//! pair). Every multi-byte integer is little-endian.
//!
//! ```
//! use aimrt_wire::{put_meta, put_str8, Reader};
//!
//! let mut out = Vec::new();
//! put_str8(&mut out, "serialization type", "pb").unwrap();
//! put_meta(&mut out, [("k", "v")]).unwrap();
//! out.extend_from_slice(b"payload");
//! assert_eq!(&out[..10], &[2, b'p', b'b', 1, 1, 0, b'k', 1, 0, b'v']);
//!
//! let mut r = Reader::new(&out);
//! assert_eq!(r.str8("serialization type").unwrap(), "pb");
//! assert_eq!(r.meta().unwrap(), [("k".to_owned(), "v".to_owned())]);
//! assert_eq!(r.rest(), b"payload");
//! ```
#![deny(unsafe_code)]

use aimrt_plugin_api::ffi::{ascii, utf8};

pub mod channel;
pub mod payload;
pub mod pending;

/// Why bytes are not a valid AimRT payload, or a value does not fit one.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// The bytes end inside a field.
    #[error("the message is cut: {what} needs {need} bytes at offset {at}, {have} remain")]
    Truncated {
        /// The field.
        what: &'static str,
        /// Where it starts.
        at: usize,
        /// How many bytes it needs.
        need: usize,
        /// How many are left.
        have: usize,
    },
    /// A text field is not UTF-8.
    #[error("the {0} is not UTF-8")]
    NotUtf8(&'static str),
    /// A field is longer than its length prefix can say.
    #[error("the {what} is {len} bytes; AimRT's layout allows at most {max}")]
    TooLong {
        /// The field.
        what: &'static str,
        /// Its length.
        len: usize,
        /// The most its prefix can say.
        max: usize,
    },
}

/// The most meta pairs a payload can carry (a `u8` count).
pub const MAX_META: usize = 255;

/// AimRT's `UrlEncode`: bytes `[A-Za-z0-9-_.~]` stay, a space becomes `+`, every other
/// byte `%XX` (uppercase hex).
///
/// ```
/// # use aimrt_wire::url_encode;
/// assert_eq!(url_encode("pb:aimrt.protocols.example.ExampleEventMsg"), "pb%3Aaimrt.protocols.example.ExampleEventMsg");
/// assert_eq!(url_encode("a b/c"), "a+b%2Fc");
/// ```
pub fn url_encode(text: &str) -> String {
    const HEX: &[u8; 16] = b"0123456789ABCDEF";
    let mut out = String::with_capacity(text.len() + 8);
    for b in text.bytes() {
        match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                out.push(char::from(b))
            }
            b' ' => out.push('+'),
            _ => {
                out.push('%');
                out.push(char::from(HEX[usize::from(b >> 4)]));
                out.push(char::from(HEX[usize::from(b & 0xF)]));
            }
        }
    }
    out
}

/// AimRT's name without prefix: everything after the first `:` of the first `:/`
/// (`pb:/pkg.Svc/M` → `/pkg.Svc/M`), else the name unchanged.
///
/// ```
/// # use aimrt_wire::name_without_prefix;
/// assert_eq!(name_without_prefix("pb:/a.B/C"), "/a.B/C");
/// assert_eq!(name_without_prefix("plain"), "plain");
/// ```
pub fn name_without_prefix(func: &str) -> &str {
    match func.find(":/") {
        Some(pos) => &func[pos + 1..],
        None => func,
    }
}

/// `Err(TooLong)` when `len > max`.
#[inline]
pub fn check_len(what: &'static str, len: usize, max: usize) -> Result<(), WireError> {
    if len > max {
        return Err(WireError::TooLong { what, len, max });
    }
    Ok(())
}

/// Appends `u8 len + text`.
#[inline]
pub fn put_str8(out: &mut Vec<u8>, what: &'static str, text: &str) -> Result<(), WireError> {
    check_len(what, text.len(), u8::MAX.into())?;
    out.push(text.len() as u8);
    out.extend_from_slice(text.as_bytes());
    Ok(())
}

/// Appends `u16_le len + text`.
pub fn put_str16(
    out: &mut Vec<u8>,
    what: &'static str,
    text: impl AsRef<[u8]>,
) -> Result<(), WireError> {
    let text = text.as_ref();
    check_len(what, text.len(), u16::MAX.into())?;
    out.extend_from_slice(&(text.len() as u16).to_le_bytes());
    out.extend_from_slice(text);
    Ok(())
}

/// Appends the meta block: `u8` pair count, then `str16` key and `str16` value per pair,
/// in the order given (AimRT accepts any order). Pairs are text or, as a context's pairs
/// cross the ABI, bytes (written as they are, not checked again).
pub fn put_meta<K: AsRef<[u8]>, V: AsRef<[u8]>>(
    out: &mut Vec<u8>,
    meta: impl IntoIterator<Item = (K, V)>,
) -> Result<(), WireError> {
    let count_at = out.len();
    out.push(0);
    let mut n = 0usize;
    for (k, v) in meta {
        n += 1;
        check_len("meta pair count", n, MAX_META)?;
        put_str16(out, "meta key", k)?;
        put_str16(out, "meta value", v)?;
    }
    out[count_at] = n as u8;
    Ok(())
}

/// The bytes [`put_meta`] writes for `meta`.
pub fn meta_len<K: AsRef<[u8]>, V: AsRef<[u8]>>(meta: impl IntoIterator<Item = (K, V)>) -> usize {
    1 + meta
        .into_iter()
        .map(|(k, v)| 4 + k.as_ref().len() + v.as_ref().len())
        .sum::<usize>()
}

/// Meta pairs borrowed from a payload, in wire order: up to 8 without an allocation.
pub type MetaRefs<'a> = smallvec::SmallVec<[(&'a str, &'a str); 8]>;

/// A meta block read in place ([`Reader::meta_block`]): every key and value in it was
/// checked as UTF-8, and its pairs are read again, without allocating, when iterated.
/// Small and `Copy`: the receive path passes it on instead of a list of pairs.
///
/// ```
/// use aimrt_wire::{put_meta, Reader};
/// let mut out = Vec::new();
/// put_meta(&mut out, [("aimrt-pub_seq", "7"), ("clé", "été")]).unwrap();
/// let meta = Reader::new(&out).meta_block().unwrap();
/// assert_eq!(meta.len(), 2);
/// let pairs: Vec<_> = meta.iter().collect();
/// assert_eq!(pairs, [("aimrt-pub_seq", "7"), ("clé", "été")]);
/// ```
#[derive(Clone, Copy)]
pub struct MetaBlock<'a> {
    /// The pairs as written: `str16` key, `str16` value.
    bytes: &'a [u8],
    /// `bytes` as text, when it is UTF-8 as a whole (AimRT's meta is ASCII, and so are
    /// length prefixes under 128) and every field starts and ends on a character
    /// boundary of it: a field is then a slice of it.
    text: Option<&'a str>,
    count: u8,
}

impl<'a> MetaBlock<'a> {
    /// How many pairs.
    pub fn len(&self) -> usize {
        self.count.into()
    }

    /// Whether there is no pair.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The pairs, in wire order.
    #[inline]
    pub fn iter(&self) -> MetaBlockIter<'a> {
        MetaBlockIter {
            spans: Spans::new(self.bytes, self.count),
            block: *self,
        }
    }

    /// Field `from..to`, checked when the block was read: a slice of the block's text
    /// (which every field then starts and ends on a character boundary of), else the
    /// field's own bytes as text.
    #[inline]
    fn field(&self, from: usize, to: usize) -> Option<&'a str> {
        match self.text {
            Some(text) => text.get(from..to),
            None => utf8(self.bytes.get(from..to)?),
        }
    }
}

impl<'a> IntoIterator for MetaBlock<'a> {
    type Item = (&'a str, &'a str);
    type IntoIter = MetaBlockIter<'a>;

    fn into_iter(self) -> MetaBlockIter<'a> {
        self.iter()
    }
}

impl std::fmt::Debug for MetaBlock<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.iter()).finish()
    }
}

impl PartialEq for MetaBlock<'_> {
    /// The same pairs in the same order.
    fn eq(&self, other: &Self) -> bool {
        self.iter().eq(other.iter())
    }
}

impl Eq for MetaBlock<'_> {}

/// The pairs of a [`MetaBlock`].
#[derive(Debug, Clone)]
pub struct MetaBlockIter<'a> {
    spans: Spans<'a>,
    block: MetaBlock<'a>,
}

impl<'a> Iterator for MetaBlockIter<'a> {
    type Item = (&'a str, &'a str);

    #[inline]
    fn next(&mut self) -> Option<(&'a str, &'a str)> {
        let (from, to) = self.spans.next()?;
        let k = self.block.field(from, to)?;
        let (from, to) = self.spans.next()?;
        Some((k, self.block.field(from, to)?))
    }
}

/// Where each field of a meta block's pairs lies (`from..to`), in order: key, value, …
/// A field cut short ends the spans (a block is checked whole before it is read so).
#[derive(Debug, Clone)]
struct Spans<'a> {
    bytes: &'a [u8],
    at: usize,
    left: usize,
}

impl<'a> Spans<'a> {
    fn new(bytes: &'a [u8], pairs: u8) -> Spans<'a> {
        Spans {
            bytes,
            at: 0,
            left: 2 * usize::from(pairs),
        }
    }
}

impl Iterator for Spans<'_> {
    type Item = (usize, usize);

    fn next(&mut self) -> Option<(usize, usize)> {
        self.left = self.left.checked_sub(1)?;
        let len = self.bytes.get(self.at..self.at + 2)?;
        let from = self.at + 2;
        let to = from + usize::from(u16::from_le_bytes([len[0], len[1]]));
        (to <= self.bytes.len()).then(|| {
            self.at = to;
            (from, to)
        })
    }
}

/// The fields of a meta pair, as errors name them.
const FIELDS: [&str; 2] = ["meta key", "meta value"];

/// Reads fields off the front of a payload; every length is checked against what remains,
/// so no input makes it panic.
#[derive(Debug, Clone)]
pub struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `bytes`.
    #[inline]
    pub fn new(bytes: &'a [u8]) -> Reader<'a> {
        Reader { bytes, at: 0 }
    }

    /// Where the next field starts.
    pub fn position(&self) -> usize {
        self.at
    }

    /// The next `need` bytes.
    #[inline]
    pub fn take(&mut self, what: &'static str, need: usize) -> Result<&'a [u8], WireError> {
        let have = self.bytes.len() - self.at;
        if need > have {
            return Err(WireError::Truncated {
                what,
                at: self.at,
                need,
                have,
            });
        }
        let s = &self.bytes[self.at..self.at + need];
        self.at += need;
        Ok(s)
    }

    /// A byte.
    #[inline]
    pub fn u8(&mut self, what: &'static str) -> Result<u8, WireError> {
        Ok(self.take(what, 1)?[0])
    }

    /// A `u16_le`.
    #[inline]
    pub fn u16(&mut self, what: &'static str) -> Result<u16, WireError> {
        let b = self.take(what, 2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    /// A `u32_le`.
    #[inline]
    pub fn u32(&mut self, what: &'static str) -> Result<u32, WireError> {
        let b = self.take(what, 4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// `n` bytes of UTF-8 text, borrowed.
    #[inline]
    pub fn text(&mut self, what: &'static str, n: usize) -> Result<&'a str, WireError> {
        let b = self.take(what, n)?;
        utf8(b).ok_or(WireError::NotUtf8(what))
    }

    /// `u8 len + text`, borrowed.
    #[inline]
    pub fn str8_ref(&mut self, what: &'static str) -> Result<&'a str, WireError> {
        let n = self.u8(what)?;
        self.text(what, n.into())
    }

    /// `u8 len + text`.
    pub fn str8(&mut self, what: &'static str) -> Result<String, WireError> {
        self.str8_ref(what).map(str::to_owned)
    }

    /// `u16_le len + text`, borrowed.
    pub fn str16_ref(&mut self, what: &'static str) -> Result<&'a str, WireError> {
        let n = self.u16(what)?;
        self.text(what, n.into())
    }

    /// The meta block [`put_meta`] writes, borrowed.
    pub fn meta_ref(&mut self) -> Result<MetaRefs<'a>, WireError> {
        Ok(self.meta_block()?.iter().collect())
    }

    /// The meta block [`put_meta`] writes, read in place: every length is checked, then
    /// every key and value as UTF-8, in one pass over the block when it is UTF-8 as a
    /// whole (else field by field; a field that is not text on its own is refused even
    /// when the block is).
    pub fn meta_block(&mut self) -> Result<MetaBlock<'a>, WireError> {
        let count = self.u8("meta pair count")?;
        let start = self.at;
        let (mut fields, mut end) = (0, 0);
        for (_, to) in Spans::new(&self.bytes[start..], count) {
            (fields, end) = (fields + 1, to);
        }
        if fields < 2 * usize::from(count) {
            // Cut short: read again field by field for the first error in wire order,
            // naming its field (a field before the cut may not be text).
            for what in FIELDS.iter().cycle().take(2 * usize::from(count)) {
                self.str16_ref(what)?;
            }
        }
        let bytes = &self.bytes[start..start + end];
        self.at = start + end;
        // An ASCII block (AimRT's meta, length prefixes under 128) is text field by field.
        // Only a byte over 127 (a character, or a length prefix) can make a field that is
        // not text on its own inside a block that is.
        if let Some(text) = ascii(bytes) {
            return Ok(MetaBlock {
                bytes,
                text: Some(text),
                count,
            });
        }
        let mut text = std::str::from_utf8(bytes).ok();
        let mut sliced = true;
        let fields = FIELDS.iter().cycle();
        for ((from, to), what) in Spans::new(bytes, count).zip(fields) {
            let whole = text.is_some_and(|t| t.is_char_boundary(from) && t.is_char_boundary(to));
            if !whole && utf8(&bytes[from..to]).is_none() {
                return Err(WireError::NotUtf8(what));
            }
            sliced &= whole;
        }
        // Fields are slices of the block's text only where each is one.
        if !sliced {
            text = None;
        }
        Ok(MetaBlock { bytes, text, count })
    }

    /// The meta block [`put_meta`] writes.
    pub fn meta(&mut self) -> Result<Vec<(String, String)>, WireError> {
        Ok(self
            .meta_ref()?
            .into_iter()
            .map(|(k, v)| (k.to_owned(), v.to_owned()))
            .collect())
    }

    /// Everything not read yet (consumed).
    #[inline]
    pub fn rest(&mut self) -> &'a [u8] {
        let s = &self.bytes[self.at..];
        self.at = self.bytes.len();
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn meta_longer_than_its_prefixes_is_refused() {
        let mut out = Vec::new();
        let many: Vec<(String, String)> =
            (0..256).map(|i| (i.to_string(), String::new())).collect();
        assert!(matches!(
            put_meta(&mut out, many.iter().map(|(k, v)| (k, v))),
            Err(WireError::TooLong { max: 255, .. })
        ));
        let long = "x".repeat(65536);
        assert!(put_meta(&mut Vec::new(), [(long.as_str(), "")]).is_err());
        assert!(put_str8(&mut Vec::new(), "t", &"y".repeat(256)).is_err());
        let mut ok = Vec::new();
        put_meta(&mut ok, [("a", "bc")]).unwrap();
        assert_eq!(ok.len(), meta_len([("a", "bc")]));
    }

    #[test]
    fn every_cut_of_a_meta_block_is_an_error_never_a_panic() {
        let mut out = Vec::new();
        put_str8(&mut out, "t", "pb").unwrap();
        put_meta(&mut out, [("key", "value"), ("k2", "v2")]).unwrap();
        for cut in 0..out.len() {
            let mut r = Reader::new(&out[..cut]);
            let parsed = r.str8("t").and_then(|_| r.meta());
            assert!(parsed.is_err(), "cut at {cut}");
        }
        let mut r = Reader::new(&out);
        r.str8("t").unwrap();
        assert_eq!(r.meta().unwrap().len(), 2);
        assert!(r.rest().is_empty());
        assert!(Reader::new(&[1, 0xff]).str8("t").is_err());
    }

    /// AimRT's meta (ASCII keys and numbers, an empty pair, a long value) reads back
    /// field by field exactly, and what follows is left; cut short anywhere, it is
    /// refused naming the field.
    #[test]
    fn an_ascii_meta_block_reads_back_and_a_cut_one_is_refused_by_field() {
        let long = "9".repeat(300);
        let pairs = [
            ("aimrt-serialization_type", "pb"),
            ("aimrt-pub_seq", "1"),
            ("", ""),
            ("k", long.as_str()),
        ];
        let mut out = Vec::new();
        put_meta(&mut out, pairs.iter().copied()).unwrap();
        out.extend_from_slice(b"rest");
        let mut r = Reader::new(&out);
        assert_eq!(r.meta_ref().unwrap().as_slice(), &pairs[..]);
        assert_eq!(r.rest(), b"rest");
        let end = out.len() - 4;
        for cut in 1..end {
            let e = Reader::new(&out[..cut]).meta_ref().unwrap_err();
            assert!(
                matches!(e, WireError::Truncated { what, .. } if what.starts_with("meta ")),
                "cut at {cut}: {e:?}"
            );
        }
    }

    /// Field by field, as the block was read before `meta_block`: the reference the
    /// one-pass check must agree with.
    fn meta_by_field<'a>(r: &mut Reader<'a>) -> Result<Vec<(&'a str, &'a str)>, WireError> {
        let count = r.u8("meta pair count")?;
        (0..count)
            .map(|_| Ok((r.str16_ref("meta key")?, r.str16_ref("meta value")?)))
            .collect()
    }

    /// Blocks of random fields (ASCII, characters, lone high bytes, bad lengths, cuts):
    /// the one-pass read gives what a field-by-field read gives, pair for pair, error
    /// for error, and stops at the same place. It never panics.
    #[test]
    fn a_meta_block_agrees_with_a_field_by_field_read_on_random_input() {
        let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        let alphabet: [&[u8]; 6] = [
            b"a",
            b"Z",
            "\u{e9}".as_bytes(),
            "\u{1f600}".as_bytes(),
            &[0x80],
            &[0xc3],
        ];
        for _ in 0..20_000 {
            let pairs = next() % 5;
            let mut out = vec![pairs as u8];
            for _ in 0..2 * pairs {
                let mut field = Vec::new();
                for _ in 0..next() % 6 {
                    // Mostly text; now and then a byte that is not.
                    let pick = (next() % 40) as usize;
                    field.extend_from_slice(
                        alphabet[if pick < 34 { pick % 4 } else { 4 + pick % 2 }],
                    );
                }
                let len = match next() % 50 {
                    0 => field.len() + 1,   // past the field
                    1 => 130 + field.len(), // a length byte over 127, past the end
                    _ => field.len(),
                };
                out.extend_from_slice(&(len as u16).to_le_bytes());
                out.extend_from_slice(&field);
            }
            if next() % 10 == 0 {
                let cut = (next() as usize) % (out.len() + 1);
                out.truncate(cut);
            }
            out.extend_from_slice(b"rest");
            let (mut a, mut b) = (Reader::new(&out), Reader::new(&out));
            let block = a.meta_block().map(|m| m.iter().collect::<Vec<_>>());
            let field = meta_by_field(&mut b);
            assert_eq!(block, field, "{out:?}");
            if block.is_ok() {
                assert_eq!(a.position(), b.position(), "{out:?}");
            }
        }
    }

    /// A block that is not text as a whole (a length byte over 127) is read field by
    /// field, and iterates to the same pairs; a cut one is refused, never read short.
    #[test]
    fn a_meta_block_reads_the_same_whether_or_not_it_is_text_as_a_whole() {
        let long = "x".repeat(200); // length 200: a prefix byte of 0xc8
        for pairs in [
            vec![("a", "1"), ("b", "")],
            vec![("k", long.as_str()), ("clé", "été")],
        ] {
            let mut out = Vec::new();
            put_meta(&mut out, pairs.iter().copied()).unwrap();
            let mut r = Reader::new(&out);
            let block = r.meta_block().unwrap();
            assert_eq!(r.position(), out.len(), "{pairs:?}");
            assert_eq!(block.len(), pairs.len());
            assert_eq!(block.iter().collect::<Vec<_>>(), pairs);
            assert_eq!(block, Reader::new(&out).meta_block().unwrap());
            assert_eq!(format!("{block:?}"), format!("{pairs:?}"));
            assert!(Reader::new(&out[..out.len() - 1]).meta_block().is_err());
        }
        assert!(std::str::from_utf8(&{
            let mut out = Vec::new();
            put_meta(&mut out, [("k", long.as_str())]).unwrap();
            out
        })
        .is_err());
    }

    /// Every meta field is checked as UTF-8 on its own, with short and long (length byte
    /// of 128 or more) fields: valid text reads back, a field that is not text is refused
    /// by name.
    #[test]
    fn meta_fields_that_are_not_utf8_are_refused() {
        let long = "é".repeat(100);
        for pairs in [
            vec![("k", "v"), ("clé", "été"), ("", "")],
            vec![("k", long.as_str()), ("clé", "été")],
        ] {
            let mut out = Vec::new();
            put_meta(&mut out, pairs.iter().copied()).unwrap();
            assert_eq!(Reader::new(&out).meta_ref().unwrap().as_slice(), &pairs[..]);
            // Each field made invalid: a lone continuation byte, a cut character.
            let at = |needle: &[u8]| out.windows(needle.len()).position(|w| w == needle);
            let e = at("été".as_bytes()).unwrap();
            for (bad, what) in [(e, "meta value"), (e + 2, "meta value")] {
                let mut broken = out.clone();
                broken[bad] = 0x80;
                assert!(
                    matches!(
                        Reader::new(&broken).meta_ref(),
                        Err(WireError::NotUtf8(w)) if w == what
                    ),
                    "byte {bad} of {pairs:?}"
                );
            }
            let c = at("clé".as_bytes()).unwrap();
            let mut broken = out.clone();
            broken[c + 2] = 0xc3; // 'é' then 0xc3 0xa9: the key ends inside a character
            broken[c + 3] = 0xc3;
            assert!(
                matches!(
                    Reader::new(&broken).meta_ref(),
                    Err(WireError::NotUtf8("meta key"))
                ),
                "{pairs:?}"
            );
        }
        // Text as a whole, yet a field cut inside a character: the key ends with 0xc3
        // and the value's length byte 0xa9 completes an 'é' across the boundary (a check
        // of the block as one text would miss it).
        let mut tricky = vec![1, 3, 0, b'c', b'l', 0xc3, 0xa9, 0];
        tricky.extend([b'x'; 0xa9]);
        assert!(std::str::from_utf8(&tricky).is_ok());
        assert!(matches!(
            Reader::new(&tricky).meta_ref(),
            Err(WireError::NotUtf8("meta key"))
        ));
    }
}
