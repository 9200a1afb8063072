//! The built-in `local` backend: delivers within the process, inline on the publisher's
//! thread or as tasks of `subscriber_executor`. It is reached only through the
//! channel-backend vtable, like a backend from a plugin.
//!
//! Within the publisher's library (same type-support table) every subscriber gets the
//! published object itself; a subscriber in another library gets its own object, decoded
//! from bytes encoded once per format for all of them.

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use aimrt_plugin_api::channel::{
    ChannelBackend, Converter, DeferredPublication, DropReason, Payload, Publication,
    PublisherInfo, Sink, Subscription,
};
use aimrt_plugin_api::ffi::{type_name_bytes_of, RawExecutor, RawMessage, TypeSupportVtable};
use aimrt_plugin_api::{BackendOptions, Error, ExecuteError, Task};

use crate::executor::serial::MAIN_THREAD_TYPE;
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
#[derive(Debug, Deserialize, serde::Serialize)]
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

/// The subscribers of one topic that take one message type, frozen at `start`.
struct Group {
    type_name: &'static str,
    /// Shared with every publication on its way to them as tasks ([`Fanout`]): beyond
    /// the group's own, each reference is one such publication, so shutdown counts them
    /// at no cost to publishing.
    sinks: Arc<[Sink]>,
}

impl Group {
    /// Publications whose deliveries have not all run (or been dropped) yet.
    fn pending(&self) -> usize {
        let n = Arc::strong_count(&self.sinks) - 1;
        // The last `Fanout` dropped its reference with release ordering: once none is
        // left, what its deliveries did is seen from here on.
        std::sync::atomic::fence(Ordering::Acquire);
        n
    }
}

/// A publication on its way to a group's subscribers as tasks: one allocation holds what
/// every task needs, so each task is two words and stored inline.
struct Fanout {
    publication: DeferredPublication,
    sinks: Arc<[Sink]>,
    executor: RawExecutor,
}

impl Fanout {
    /// Delivers to subscriber `i` on this thread.
    fn deliver(&self, i: usize) {
        let (p, sink) = (&self.publication, &self.sinks[i]);
        let ts = sink.type_support();
        match object(p.payload_for(ts), ts) {
            // A failed subscriber is counted and logged by the sink.
            Ok(msg) => drop(sink.deliver(&p.meta(), msg)),
            Err((reason, why)) => sink.report_drop(reason, &why),
        }
    }

    /// Posts the delivery to subscriber `i`; a refusal is reported to it.
    fn post(self: &Arc<Self>, i: usize) {
        let me = self.clone();
        let task = Task::new(move || me.deliver(i));
        if let Err(e) = ExecuteError::from_status(self.executor.execute(task)) {
            self.sinks[i].report_drop(
                DropReason::Refused,
                &format!("subscriber_executor refused the delivery: {e}"),
            );
        }
    }

    /// Runs on the executor when the group has several subscribers: posts the others'
    /// deliveries, then delivers to the first here.
    fn fan_out(self: &Arc<Self>) {
        for i in 1..self.sinks.len() {
            self.post(i);
        }
        self.deliver(0);
    }
}

pub(crate) struct LocalBackend {
    executors: HashMap<String, RawExecutor>,
    /// Where subscribers run (`None`: inline), set by `init`.
    executor: OnceLock<Option<RawExecutor>>,
    /// Subscriptions by topic, collected while modules initialize.
    pending: Mutex<HashMap<String, Vec<LocalSub>>>,
    /// The same by type, frozen at `start`: publishing reads it without a lock, so a
    /// subscriber that publishes (inline, on the publisher's thread) never waits on this
    /// backend. Keyed by the topic's bytes with a fast hash: looked up per message, without
    /// checking the topic as UTF-8 again.
    subs: OnceLock<HashMap<Box<[u8]>, Vec<Group>, foldhash::fast::RandomState>>,
    /// How long `shutdown` waits for them (`aimrt.executor.join_timeout_ms`).
    drain_timeout: Duration,
}

impl LocalBackend {
    pub(crate) fn new(
        executors: HashMap<String, RawExecutor>,
        drain_timeout: Duration,
    ) -> LocalBackend {
        LocalBackend {
            executors,
            executor: OnceLock::new(),
            pending: Mutex::new(HashMap::new()),
            subs: OnceLock::new(),
            drain_timeout,
        }
    }
}

impl ChannelBackend for LocalBackend {
    fn type_name(&self) -> &str {
        "local"
    }

    fn init(&self, options: &BackendOptions) -> Result<(), Error> {
        let o: LocalOptions = options.read()?;
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
        let pending = std::mem::take(&mut *self.pending.lock().unwrap_or_else(|e| e.into_inner()));
        let subs = pending
            .into_iter()
            .map(|(topic, list)| {
                let mut groups: Vec<Group> = Vec::new();
                for sub in &list {
                    if groups.iter().all(|g| g.type_name != sub.type_name) {
                        let sinks = list.iter().filter(|s| s.type_name == sub.type_name);
                        groups.push(Group {
                            type_name: sub.type_name,
                            sinks: sinks.map(|s| s.sink.clone()).collect(),
                        });
                    }
                }
                (topic.into_bytes().into_boxed_slice(), groups)
            })
            .collect();
        let _ = self.subs.set(subs);
        Ok(())
    }

    /// Waits until every delivery posted to `subscriber_executor` has run (at most
    /// `join_timeout_ms`), so the subscribers, a recording plugin's among them, get every
    /// message published before shutdown while they still take them. Publishing is refused
    /// from now on (the channel has shut down), so the wait ends. It is skipped for the
    /// main thread's executor (and any this thread serves): the thread shutting down
    /// runs those tasks itself, after the plugins.
    fn shutdown(&self) {
        let Some(executor) = self.executor.get().copied().flatten() else {
            return;
        };
        if executor.type_name() == MAIN_THREAD_TYPE || executor.is_in_current_executor() {
            return;
        }
        let deadline = Instant::now() + self.drain_timeout;
        loop {
            let left: usize = self
                .subs
                .get()
                .into_iter()
                .flat_map(|topics| topics.values().flatten())
                .map(Group::pending)
                .sum();
            if left == 0 {
                return;
            }
            if Instant::now() >= deadline {
                tracing::warn!(target: "aimrt",
                    "local channel backend: {left} publications still wait on subscriber_executor '{}' after {} ms; shutdown goes on, and subscribers that have shut down by the time they run may refuse them",
                    executor.name(),
                    self.drain_timeout.as_millis()
                );
                return;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
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
        let type_name = type_name_bytes_of(publication.message().type_support());
        let Some(group) = self
            .subs
            .get()
            .and_then(|subs| subs.get(publication.topic_bytes()))
            .and_then(|groups| groups.iter().find(|g| g.type_name.as_bytes() == type_name))
        else {
            return Ok(0);
        };
        let receivers = group.sinks.len() as u64;
        let Some(executor) = self.executor.get().copied().flatten() else {
            let mut converter = Converter::new(publication);
            for sink in group.sinks.iter() {
                let ts = sink.type_support();
                match object(converter.payload_for(ts), ts) {
                    // A failed subscriber is counted and logged by the sink.
                    Ok(msg) => drop(sink.deliver(publication.meta(), msg)),
                    Err((reason, why)) => sink.report_drop(reason, &why),
                }
            }
            return Ok(receivers);
        };
        // Delivered as tasks. The publisher pays for one copy of the context and one post
        // however many subscribers there are: with several, the posted task posts the
        // others' deliveries from the executor, then delivers to the first. Converting for
        // a subscriber of another library (encode, decode) happens in its task, the bytes
        // shared between such tasks.
        let fanout = Arc::new(Fanout {
            publication: DeferredPublication::new(publication),
            sinks: group.sinks.clone(),
            executor,
        });
        if group.sinks.len() == 1 {
            fanout.post(0);
            return Ok(receivers);
        }
        let task = Task::new({
            let fanout = fanout.clone();
            move || fanout.fan_out()
        });
        if let Err(e) = ExecuteError::from_status(executor.execute(task)) {
            let why = format!("subscriber_executor refused the delivery: {e}");
            for sink in group.sinks.iter() {
                sink.report_drop(DropReason::Refused, &why);
            }
        }
        Ok(receivers)
    }
}
