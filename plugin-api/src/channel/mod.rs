//! Channels: publish/subscribe of typed messages with a per-message [`Context`].
//!
//! - Modules get a [`ChannelRef`] from [`CoreRef::channel`](crate::CoreRef::channel), make
//!   [`Publisher`]s and subscribe through [`Subscriber`]s (see `docs/channels.md`).
//! - Message types implement [`Message`]; [`serde_message!`](crate::serde_message) writes
//!   it for serde types.
//! - Backends (the built-in `local`, or one from a plugin) implement [`ChannelBackend`].

mod api;
mod backend;
mod context;
mod filter;
pub(crate) mod message;
// Its number formatting serves hand-written JSON too (`json_double`); the rest, protobuf.
#[cfg_attr(not(feature = "prost"), allow(dead_code))]
mod proto_json;
mod proto_json_read;
mod registry;
mod stats;
#[cfg(feature = "prost")]
mod well_known;

pub(crate) use crate::ffi::pubsub::Callback;

pub use self::api::{ChannelRef, Publisher, Subscriber};
pub use self::backend::{
    ChannelBackend, Converter, DeferredPublication, LossReporter, Payload, Publication,
    PublisherInfo, Sink, Subscription, RECEIVERS_UNKNOWN,
};
pub use self::context::{
    Context, ContextKind, KEY_BACKEND, KEY_PUB_SEQ, KEY_PUB_TS, KEY_SERIALIZATION_TYPE, KEY_TO_ADDR,
};
pub use self::filter::{ChannelFilter, FilterSide, Next};
#[cfg(feature = "prost")]
pub use self::message::{pb_deserialize, pb_encode_to_slice, pb_encoded_len, pb_serialize};
pub use self::message::{
    serde_deserialize, serde_encode_to_slice, serde_encoded_len, serde_serialize, Message,
    MessageError, Schema, PB_FORMATS, SERDE_FORMATS,
};
pub use self::proto_json::json_double;
pub use self::registry::TopicRegistry;
pub use self::stats::{DropReason, TopicStats};
