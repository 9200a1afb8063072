//! What every channel backend of AimRT's transports does the same way: encode a
//! publication in its context's serialization type, and hand a received message to the
//! subscribers of its topic with AimRT's context (the serialization type, then the wire
//! meta; the sink adds `aimrt-backend`).

use std::borrow::Cow;

use aimrt_plugin_api::channel::{DropReason, Publication, Sink, KEY_SERIALIZATION_TYPE};
use aimrt_plugin_api::ffi::{formats_of, MetaPair, MetaPairs, RawMessage};

/// The format a publication travels in: its context's serialization type, else its
/// type's first.
pub fn format_of<'a>(publication: &Publication<'a>) -> Cow<'a, str> {
    match publication.get(KEY_SERIALIZATION_TYPE) {
        Some(f) => Cow::Borrowed(f),
        None => Cow::Owned(
            formats_of(publication.message().type_support())
                .into_iter()
                .next()
                .unwrap_or_default(),
        ),
    }
}

/// A publication's message encoded in `format`, appended to `out`; `Err` says why it
/// cannot be.
pub fn encode_into(
    publication: &Publication<'_>,
    format: &str,
    out: &mut Vec<u8>,
) -> Result<(), String> {
    publication
        .message()
        .encode_into(format, out)
        .map_err(|e| format!("cannot encode the message as {format}: {e}"))
}

/// A publication's message encoded in `format` straight into the buffer `room` gives
/// (see [`RawMessage::encode_to`]); `Err` says why it cannot be encoded, or is `room`'s.
pub fn encode_to<T, F>(publication: &Publication<'_>, format: &str, room: F) -> Result<T, String>
where
    T: AsMut<[u8]>,
    F: FnOnce(usize) -> Result<(T, usize), String>,
{
    let mut refused = None;
    publication
        .message()
        .encode_to(format, |len| {
            room(len).inspect_err(|e| refused = Some(e.clone()))
        })
        .map_err(|e| match refused {
            Some(own) => own,
            None => format!("cannot encode the message as {format}: {e}"),
        })
}

/// A publication's message encoded in its [`format_of`]: `(format, bytes)`; `Err` says
/// why it cannot be.
pub fn encoded<'a>(publication: &Publication<'a>) -> Result<(Cow<'a, str>, Vec<u8>), String> {
    let format = format_of(publication);
    let mut payload = Vec::new();
    encode_into(publication, &format, &mut payload)?;
    Ok((format, payload))
}

/// Delivers one received message to `sinks`: each decodes it for its own type, and one
/// that cannot reports the drop ([`DropReason::DecodeFailed`]) with `from` in the detail
/// (the runtime's report names the backend). The context is AimRT's: the serialization
/// type, then the wire meta (a wire pair of the same key replaces it).
pub fn deliver<'m>(
    sinks: &[Sink],
    serialization_type: &'m str,
    meta: impl IntoIterator<Item = (&'m str, &'m str)>,
    payload: &[u8],
    from: &dyn std::fmt::Display,
) {
    // Built in place (not collected and moved): it is per message.
    let mut pairs = MetaPairs::default();
    pairs.push(MetaPair::new(KEY_SERIALIZATION_TYPE, serialization_type));
    for (k, v) in meta {
        pairs.set(k, v);
    }
    for sink in sinks {
        match RawMessage::decode(sink.type_support(), serialization_type, payload) {
            Ok(msg) => {
                let _ = sink.deliver(&pairs, msg);
            }
            Err(e) => sink.report_drop(
                DropReason::DecodeFailed,
                &format!("a message from {from} cannot be decoded ({serialization_type}): {e}"),
            ),
        }
    }
}
