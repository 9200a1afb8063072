//! The built-in `local` backend: delivers within the process, inline on the publisher's
//! thread or as tasks of `subscriber_executor`. It is reached only through the
//! channel-backend vtable, like a backend from a plugin.
//!
//! Within the publisher's library (same type-support table) every subscriber gets the
//! published object itself; a subscriber in another library gets its own object, decoded
//! from bytes encoded once per format for all of them.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

use aimrt_plugin_api::channel::{
    ChannelBackend, Converter, DeferredPublication, DropReason, Payload, Publication,
    PublisherInfo, Sink, Subscription,
};
use aimrt_plugin_api::ffi::{type_name_of, RawExecutor, RawMessage, TypeSupportVtable};
use aimrt_plugin_api::{BackendOptions, Error, ExecuteError, Task};
use serde::Deserialize;

/// The object a subscriber of table `ts` gets from its payload, or why it gets none.
fn object(
    payload: Result<Payload, (DropReason, String)>,
    ts: &'static TypeSupportVtable,
) -> Result<RawMessage, (DropReason, String)> {
    payload.and_then(|p| {
        p.into_message(ts)
            .map_err(|why| (DropReason::DecodeFailed, why))
    })
}

/// Options of `local`, as AimRT.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LocalOptions {
    #[serde(default = "yes")]
    subscriber_use_inline_executor: bool,
    #[serde(default)]
    subscriber_executor: String,
}

fn yes() -> bool {
    true
}

struct LocalSub {
    type_name: &'static str,
    sink: Sink,
}

pub(crate) struct LocalBackend {
    executors: HashMap<String, RawExecutor>,
    /// Where subscribers run (`None`: inline), set by `init`.
    executor: OnceLock<Option<RawExecutor>>,
    /// Subscriptions by topic, collected while modules initialize.
    pending: Mutex<HashMap<String, Vec<LocalSub>>>,
    /// The same, frozen at `start`: publishing reads it without a lock, so a subscriber
    /// that publishes (inline, on the publisher's thread) never waits on this backend.
    subs: OnceLock<HashMap<String, Vec<LocalSub>>>,
}

impl LocalBackend {
    pub(crate) fn new(executors: HashMap<String, RawExecutor>) -> LocalBackend {
        LocalBackend {
            executors,
            executor: OnceLock::new(),
            pending: Mutex::new(HashMap::new()),
            subs: OnceLock::new(),
        }
    }
}

impl ChannelBackend for LocalBackend {
    fn type_name(&self) -> &str {
        "local"
    }

    fn init(&self, options: &BackendOptions) -> Result<(), Error> {
        let o: LocalOptions = options.get()?;
        let executor = if o.subscriber_use_inline_executor {
            None
        } else {
            let name = o.subscriber_executor;
            if name.is_empty() {
                return Err(Error::msg("subscriber_use_inline_executor is false, so subscriber_executor must name the executor that runs the subscribers"));
            }
            let Some(raw) = self.executors.get(&name) else {
                return Err(Error::msg(format!(
                    "subscriber_executor '{name}' is not an executor{}",
                    aimrt_plugin_api::__private::did_you_mean(
                        &name,
                        self.executors.keys().map(String::as_str)
                    )
                )));
            };
            Some(*raw)
        };
        let _ = self.executor.set(executor);
        Ok(())
    }

    fn start(&self) -> Result<(), Error> {
        let subs = std::mem::take(&mut *self.pending.lock().unwrap_or_else(|e| e.into_inner()));
        let _ = self.subs.set(subs);
        Ok(())
    }

    fn register_publish_type(&self, _: &PublisherInfo<'_>) -> Result<(), Error> {
        Ok(())
    }

    fn subscribe(&self, subscription: Subscription) -> Result<(), Error> {
        let sub = LocalSub {
            type_name: subscription.sink.type_name(),
            sink: subscription.sink,
        };
        if self.subs.get().is_some() {
            return Err(Error::msg(
                "the local backend has started; subscribe in initialize",
            ));
        }
        self.pending
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(subscription.topic)
            .or_default()
            .push(sub);
        Ok(())
    }

    fn publish(&self, publication: &Publication<'_>) -> Result<u64, Error> {
        let Some(list) = self
            .subs
            .get()
            .and_then(|subs| subs.get(publication.topic()))
        else {
            return Ok(0);
        };
        let type_name = type_name_of(publication.message().type_support());
        let executor = self.executor.get().copied().flatten();
        let mut receivers = 0;
        let Some(executor) = executor else {
            let mut converter = Converter::new(publication);
            for sub in list.iter().filter(|s| s.type_name == type_name) {
                receivers += 1;
                let ts = sub.sink.type_support();
                match object(converter.payload_for(ts), ts) {
                    // A failed subscriber is counted and logged by the sink.
                    Ok(msg) => drop(sub.sink.deliver(publication.meta(), msg)),
                    Err((reason, why)) => sub.sink.report_drop(reason, &why),
                }
            }
            return Ok(receivers);
        };
        // Delivered as tasks: the publisher pays for one copy of the context and one post
        // per subscriber; converting for a subscriber of another library (encode, decode)
        // happens in its task, the bytes shared between such tasks.
        let mut kept: Option<Arc<DeferredPublication>> = None;
        for sub in list.iter().filter(|s| s.type_name == type_name) {
            receivers += 1;
            let p = kept
                .get_or_insert_with(|| Arc::new(DeferredPublication::new(publication)))
                .clone();
            let (sink, ts) = (sub.sink.clone(), sub.sink.type_support());
            // Four words (the sink, the publication, the table): stored inline in the
            // task, no allocation.
            let task = Task::new(move || match object(p.payload_for(ts), ts) {
                Ok(msg) => drop(sink.deliver(&p.meta(), msg)),
                Err((reason, why)) => sink.report_drop(reason, &why),
            });
            if let Err(e) = ExecuteError::from_status(executor.execute(task)) {
                sub.sink.report_drop(
                    DropReason::Refused,
                    &format!("subscriber_executor refused the delivery: {e}"),
                );
            }
        }
        Ok(receivers)
    }
}
