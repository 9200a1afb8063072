//! What a publish allocates once the process runs: nothing, with a subscriber in the same
//! library delivered inline by `local`, and also when nobody subscribes (every message is
//! then dropped and counted) or nothing routes the topic. A test binary
//! of its own, because it replaces the allocator; it counts the allocations of the
//! publishing thread only, so the runtime's other threads cannot disturb the count.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use aimrt_plugin_api::channel::{DropReason, Publisher};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use aimrt_runtime::{Runtime, RuntimeOptions};

thread_local! {
    // A const-initialised `Cell` without a destructor: reading it never allocates.
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

struct PerThread;

// SAFETY: forwards to `System`; the count is a thread-local `Cell` that never allocates.
unsafe impl GlobalAlloc for PerThread {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|n| n.set(n.get() + 1));
        // SAFETY: the caller's contract, forwarded.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller's contract, forwarded.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = ALLOCATIONS.try_with(|n| n.set(n.get() + 1));
        // SAFETY: the caller's contract, forwarded.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: PerThread = PerThread;

fn allocations() -> u64 {
    ALLOCATIONS.with(Cell::get)
}

#[derive(Debug, serde::Serialize, serde::Deserialize)]
struct Reading {
    value: u64,
}
aimrt_plugin_api::serde_message!(Reading, "test.Reading");

/// What the module saw: allocations of `N` publishes per topic, after one each.
#[derive(Debug, Default)]
struct Seen {
    per_topic: Vec<(&'static str, u64)>,
    dropped: Vec<(&'static str, u64)>,
}

const N: u64 = 1_000;
/// `/somebody` has a subscriber; `/nobody` is routed to `local` and nobody subscribes;
/// `/nowhere` matches no rule.
const TOPICS: [&str; 3] = ["/somebody", "/nobody", "/nowhere"];

struct Publishing {
    seen: Arc<Mutex<Seen>>,
    received: Arc<AtomicU64>,
    publishers: Vec<(&'static str, Publisher<Reading>)>,
    channel: Option<aimrt_plugin_api::channel::ChannelRef>,
}

impl Module for Publishing {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("Publishing")
    }
    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let channel = core.channel()?;
        let received = self.received.clone();
        channel
            .subscriber("/somebody")
            .subscribe_msg(move |r: Arc<Reading>| {
                received.fetch_add(r.value, Ordering::Relaxed);
            })?;
        for topic in TOPICS {
            self.publishers.push((topic, channel.publisher(topic)?));
        }
        self.channel = Some(channel);
        Ok(())
    }
    fn start(&mut self) -> Result<(), Error> {
        let message = Arc::new(Reading { value: 7 });
        let mut seen = Seen::default();
        for (topic, p) in &self.publishers {
            // The first publish seals the registries and logs the first drop.
            p.publish(message.clone())?;
            let before = allocations();
            for _ in 0..N {
                p.publish(message.clone())?;
            }
            seen.per_topic.push((topic, allocations() - before));
            let stats = self.channel.as_ref().and_then(|c| c.stats(topic));
            let dropped = stats.map_or(0, |s| {
                s.dropped_for(DropReason::NoSubscriber) + s.dropped_for(DropReason::NoRoute)
            });
            seen.dropped.push((topic, dropped));
        }
        *self.seen.lock().unwrap() = seen;
        Ok(())
    }
}

#[test]
fn a_publish_nobody_receives_allocates_nothing_and_is_counted() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cfg.yaml");
    std::fs::write(
        &path,
        "aimrt:\n  channel:\n    backends:\n      - type: local\n    pub_topics_options:\n      - topic_name: \"/no.*|/some.*\"\n        enable_backends: [local]\n    sub_topics_options:\n      - topic_name: \"/somebody\"\n        enable_backends: [local]\n",
    )
    .unwrap();
    let seen = Arc::new(Mutex::new(Seen::default()));
    let received = Arc::new(AtomicU64::new(0));
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: Some(path),
        running_duration: Some(Duration::from_millis(50)),
        ..Default::default()
    });
    runtime.register_module(Box::new(Publishing {
        seen: seen.clone(),
        received: received.clone(),
        publishers: Vec::new(),
        channel: None,
    }));
    runtime.run().expect("runs");
    let seen = seen.lock().unwrap();
    assert_eq!(
        received.load(Ordering::Relaxed),
        7 * (N + 1),
        "every message on /somebody is delivered"
    );
    assert_eq!(
        seen.dropped,
        [("/somebody", 0), ("/nobody", N + 1), ("/nowhere", N + 1)],
        "every message nobody receives is counted as dropped"
    );
    assert_eq!(
        seen.per_topic,
        [("/somebody", 0), ("/nobody", 0), ("/nowhere", 0)],
        "allocations of {N} publishes on the publishing thread"
    );
}
