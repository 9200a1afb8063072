//! Channels: publish/subscribe of typed messages with a per-message [`Context`].

mod context;
mod message;

pub use self::context::{
    Context, ContextKind, KEY_BACKEND, KEY_PUB_SEQ, KEY_PUB_TS, KEY_SERIALIZATION_TYPE, KEY_TO_ADDR,
};
pub use self::message::{serde_deserialize, serde_serialize, Message, MessageError, SERDE_FORMATS};
