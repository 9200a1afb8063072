//! AimRT's `pb_chn` channel examples in Rust, with AimRT's module names and config keys,
//! so that AimRT's `examples_cpp_pb_chn_*` configs run with only the pkg paths changed:
//!
//! | module | what it does | config keys |
//! |---|---|---|
//! | `NormalPublisherModule` | publishes an `ExampleEventMsg` `channel_frq` times a second from a loop on `work_thread_pool` | `topic_name`, `channel_frq`; ours: `serialization_type`, `context_meta`, `msg_size` |
//! | `NormalSubscriberModule` | logs each message with its context | `topic_name` |
//! | `AsyncSubscriberModule` | handles each message in an async task on `executor` | `topic_name`, `executor` |
//! | `RelayModule` | republishes what it receives on another topic, carrying the context's user keys over | `sub_topic_name`, `pub_topic_name` |
//! | `BenchmarkPublisherModule` | AimRT's channel benchmark: runs `bench_plans`, framed by signals on `benchmark_signal`, on `test_topic_<i>` | `max_topic_number`, `max_parallel_number`, `bench_plans` |
//! | `BenchmarkSubscriberModule` | receives the benchmark and logs a latency and loss report per plan | `max_topic_number` |
//!
//! The modules live in this rlib; the `pb_chn_pkg`, `pb_chn_pub_pkg` and `pb_chn_sub_pkg`
//! crates are cdylib shells of a few lines that export them.
#![deny(unsafe_code)]

pub mod benchmark;
mod publisher;
mod subscriber;

pub use benchmark::{BenchmarkPublisherModule, BenchmarkSubscriberModule};
pub use publisher::NormalPublisherModule;
pub use subscriber::{AsyncSubscriberModule, NormalSubscriberModule, RelayModule};

/// The message of the examples.
pub use aimrt_protocols::example::ExampleEventMsg;

/// The message as one line of JSON (AimRT's `Pb2CompactJson`).
///
/// A `msg` longer than [`LOGGED_MSG_LEN`] bytes is shown by its length
/// (`{"msg":"<1048576 bytes>","num":3}`), so large-message runs keep readable logs.
pub fn to_json(msg: &ExampleEventMsg) -> String {
    if msg.msg.len() > LOGGED_MSG_LEN {
        let short = ExampleEventMsg {
            msg: format!("<{} bytes>", msg.msg.len()),
            num: msg.num,
        };
        return to_json(&short);
    }
    serde_json::to_string(msg).unwrap_or_else(|e| format!("<not json: {e}>"))
}

/// The longest `msg` [`to_json`] shows in full.
pub const LOGGED_MSG_LEN: usize = 256;
