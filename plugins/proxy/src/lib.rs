//! `proxy_plugin`: forwards every message of some topics to other topics, as AimRT's
//! proxy_plugin does. With the channel rules routing the subscribed topic to one backend
//! and the published topics to another, it bridges backends: messages that arrive over
//! `http` go out over `zenoh`, say. The message types come from type support packages
//! (`type_support_pkgs`), so the plugin needs no Rust type of its own.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: proxy_plugin
//!         path: ./target/debug/libaimrt_proxy_plugin.so
//!         options:
//!           type_support_pkgs:
//!             - path: ./target/debug/libexample_pb_ts.so
//!           proxy_actions:
//!             - name: my_proxy
//!               options:
//!                 executor: proxy_plugin_executor     # thread safe: keeps the order
//!                 topic_meta_list:
//!                   - sub_topic_name: test_topic_http
//!                     pub_topic_name: [test_topic_zenoh]
//!                     msg_type: pb:aimrt.protocols.example.ExampleEventMsg
//! ```
//!
//! Each message received on a `sub_topic_name` is handed to its action's executor, which
//! publishes it on every `pub_topic_name` with a new context carrying the received
//! context's own keys (not the `aimrt-` ones: each hop has its own sequence, time stamp,
//! format and backend). AimRT's proxy forwards no keys at all.
#![deny(unsafe_code)]

use std::collections::HashSet;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};

use aimrt_plugin_api::channel::{ChannelRef, Context, ContextKind};
use aimrt_plugin_api::ffi::{RawMessage, TypeSupportVtable};
use aimrt_plugin_api::{
    CoreRef, Error, ExecutorRef, Plugin, PluginOptions, RateLimit, Registrar, TypeSupportPkg,
};
use serde::Deserialize;

/// One topic an action forwards, and where to.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct TopicMeta {
    sub_topic_name: String,
    pub_topic_name: Vec<String>,
    msg_type: String,
}

#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct ActionOptions {
    #[serde(default)]
    executor: String,
    #[serde(default)]
    topic_meta_list: Vec<TopicMeta>,
}

#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct ProxyAction {
    name: String,
    options: ActionOptions,
}

#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    type_support_pkgs: Vec<TypeSupportPkg>,
    /// Read by AimRT and never used: each action names its own executor.
    #[serde(default)]
    executor: String,
    #[serde(default)]
    proxy_actions: Vec<ProxyAction>,
}

/// What the options ask the plugin to subscribe and publish, checked before anything is
/// registered.
#[derive(Debug, PartialEq, Eq)]
struct Plan {
    actions: Vec<PlannedAction>,
    /// Warnings to log (a route into its own subscription).
    warnings: Vec<String>,
}

#[derive(Debug, PartialEq, Eq)]
struct PlannedAction {
    name: String,
    executor: String,
    routes: Vec<Route>,
}

/// Messages of `msg_type` on `sub` are published on each topic of `to`.
#[derive(Debug, PartialEq, Eq)]
struct Route {
    sub: String,
    msg_type: String,
    to: Vec<String>,
}

/// Checks `o` against the known type names (`has_type` says whether a type is known, or
/// why not) and returns what to subscribe and publish.
fn plan(o: &Options, has_type: impl Fn(&str) -> Result<(), String>) -> Result<Plan, String> {
    let mut names = HashSet::new();
    let mut subs = HashSet::new();
    let mut pubs = HashSet::new();
    let mut actions = Vec::new();
    let mut warnings = Vec::new();
    for (a, action) in o.proxy_actions.iter().enumerate() {
        let at = format!("proxy_actions[{a}] ('{}')", action.name);
        if action.name.is_empty() {
            return Err(format!(
                "proxy_actions[{a}].name is empty; give each action a name"
            ));
        }
        if !names.insert(action.name.as_str()) {
            return Err(format!("{at}: the name is used by an earlier action"));
        }
        let opts = &action.options;
        if opts.executor.is_empty() {
            return Err(format!("{at}: options.executor is required: the executor that publishes the action's messages; a thread-safe one (simple_thread, asio_thread with thread_num 1, asio_strand) keeps their order"));
        }
        let mut routes = Vec::new();
        for (j, t) in opts.topic_meta_list.iter().enumerate() {
            let tat = format!("{at}: topic_meta_list[{j}]");
            if t.sub_topic_name.is_empty() {
                return Err(format!("{tat}.sub_topic_name is empty"));
            }
            has_type(&t.msg_type).map_err(|e| format!("{tat}.{e}"))?;
            if t.pub_topic_name.is_empty() {
                return Err(format!(
                    "{tat}.pub_topic_name is empty; list the topics '{}' is forwarded to",
                    t.sub_topic_name
                ));
            }
            if !subs.insert((t.sub_topic_name.as_str(), t.msg_type.as_str())) {
                return Err(format!(
                    "{tat}: topic '{}' with type '{}' is subscribed twice (sub_topic_name)",
                    t.sub_topic_name, t.msg_type
                ));
            }
            for (k, p) in t.pub_topic_name.iter().enumerate() {
                if p.is_empty() {
                    return Err(format!("{tat}.pub_topic_name[{k}] is empty"));
                }
                if !pubs.insert((p.as_str(), t.msg_type.as_str())) {
                    return Err(format!(
                        "{tat}.pub_topic_name[{k}]: topic '{p}' with type '{}' is published twice",
                        t.msg_type
                    ));
                }
                if *p == t.sub_topic_name {
                    warnings.push(format!("{tat}: topic '{p}' is forwarded to itself; a backend that carries both directions hands every forwarded message back to the proxy"));
                }
            }
            routes.push(Route {
                sub: t.sub_topic_name.clone(),
                msg_type: t.msg_type.clone(),
                to: t.pub_topic_name.clone(),
            });
        }
        actions.push(PlannedAction {
            name: action.name.clone(),
            executor: opts.executor.clone(),
            routes,
        });
    }
    Ok(Plan { actions, warnings })
}

/// One action at run time: where it publishes from and what happened to its messages.
struct Forwarder {
    name: String,
    channel: ChannelRef,
    /// Set once everything has started (publishing is allowed from then on).
    executor: OnceLock<ExecutorRef>,
    running: AtomicBool,
    received: AtomicU64,
    /// Messages the executor did not take (reported to the delivering backend).
    refused: AtomicU64,
    forwarded: AtomicU64,
    failed: AtomicU64,
    dropped_at_shutdown: AtomicU64,
    warn: RateLimit,
}

impl Forwarder {
    /// Hands `msg`, received with `ctx`, to the executor, which publishes it on `to`.
    fn accept(
        self: &Arc<Self>,
        to: &Arc<[String]>,
        ctx: &Context,
        msg: RawMessage,
    ) -> Result<(), String> {
        self.received.fetch_add(1, Ordering::Relaxed);
        let Some(executor) = self.executor.get() else {
            self.refused.fetch_add(1, Ordering::Relaxed);
            return Err(format!(
                "proxy action '{}' has not started: the message is not forwarded",
                self.name
            ));
        };
        let mut out = Context::new(ContextKind::Publish);
        out.merge_from(ctx);
        let (me, to) = (self.clone(), to.clone());
        executor
            .execute(move || me.publish(&to, &out, msg))
            .map_err(|e| {
                self.refused.fetch_add(1, Ordering::Relaxed);
                format!(
                    "proxy action '{}': the message is not forwarded: {e}",
                    self.name
                )
            })
    }

    /// Publishes `msg` on every topic of `to` (on the action's executor).
    fn publish(&self, to: &[String], ctx: &Context, msg: RawMessage) {
        if !self.running.load(Ordering::Acquire) {
            // Still queued when the plugin shut down: after its summary line, so said here.
            let n = self.dropped_at_shutdown.fetch_add(1, Ordering::Relaxed) + 1;
            if self.warn.ready() {
                tracing::warn!(
                    "proxy action '{}': a message still queued at shutdown is dropped ({n} so far)",
                    self.name
                );
            }
            return;
        }
        for topic in to {
            match self.channel.publish_raw(topic, ctx, msg.share()) {
                Ok(()) => {
                    self.forwarded.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => {
                    self.failed.fetch_add(1, Ordering::Relaxed);
                    if let Some(held) = self.warn.admit() {
                        tracing::warn!(
                            "proxy action '{}': cannot forward to topic '{topic}': {e} ({held} more such failures since the last warning)",
                            self.name
                        );
                    }
                }
            }
        }
    }

    /// The action's counters, as one line.
    fn summary(&self) -> String {
        let n = |c: &AtomicU64| c.load(Ordering::Relaxed);
        format!(
            "proxy action '{}': {} messages received, {} publications forwarded, {} failed, {} refused by the executor or before the start, {} dropped at shutdown",
            self.name,
            n(&self.received),
            n(&self.forwarded),
            n(&self.failed),
            n(&self.refused),
            n(&self.dropped_at_shutdown)
        )
    }
}

#[derive(Default)]
struct ProxyPlugin {
    core: Option<CoreRef>,
    /// Each action with the name of its executor.
    actions: Vec<(Arc<Forwarder>, String)>,
    /// The executors found at start, given to the actions at post-start.
    executors: Vec<ExecutorRef>,
}

/// The plugin, as `libaimrt_proxy_plugin.so` exports it (`plugins/proxy/so`).
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(ProxyPlugin::default())
}

impl Plugin for ProxyPlugin {
    fn name(&self) -> &str {
        "proxy_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: Options = registrar.read_options(options)?;
        let bad = |message: String| options.invalid(message);
        let types = registrar
            .load_type_support_pkgs(&o.type_support_pkgs)
            .map_err(bad)?;
        let plan = plan(&o, |t| types.get(t).map(drop)).map_err(bad)?;
        if !o.executor.is_empty() {
            tracing::warn!("proxy_plugin: option 'executor: {}' is not used (AimRT reads it and does not use it either); each action's options.executor publishes its messages", o.executor);
        }
        for w in &plan.warnings {
            tracing::warn!("proxy_plugin: {w}");
        }
        let core = registrar.core()?;
        let channel = core.channel()?;
        for action in plan.actions {
            let fwd = Arc::new(Forwarder {
                name: action.name,
                channel,
                executor: OnceLock::new(),
                running: AtomicBool::new(false),
                received: AtomicU64::new(0),
                refused: AtomicU64::new(0),
                forwarded: AtomicU64::new(0),
                failed: AtomicU64::new(0),
                dropped_at_shutdown: AtomicU64::new(0),
                warn: RateLimit::from_millis(1000),
            });
            for route in action.routes {
                let ts: &'static TypeSupportVtable = types.get(&route.msg_type).map_err(bad)?;
                for p in &route.to {
                    channel.register_publish_raw(p, ts)?;
                }
                let to: Arc<[String]> = route.to.into();
                let f = fwd.clone();
                channel.subscribe_raw(&route.sub, ts, move |ctx, msg| f.accept(&to, ctx, msg))?;
            }
            self.actions.push((fwd, action.executor));
        }
        self.core = Some(core);
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(core) = self.core else {
            return Ok(());
        };
        for (fwd, name) in &self.actions {
            let e = core.executor(name).map_err(|_| {
                Error::msg(format!(
                    "proxy_plugin: the executor '{name}' of proxy action '{}' is not an executor of aimrt.executor.executors",
                    fwd.name
                ))
            })?;
            if !e.thread_safe() {
                return Err(Error::msg(format!(
                    "proxy_plugin: Proxy executor {name} is not thread safe! (proxy action '{}'): its tasks may run at once and reorder the messages; use a serial one: simple_thread, asio_thread with thread_num 1, or asio_strand",
                    fwd.name
                )));
            }
            self.executors.push(e);
        }
        Ok(())
    }

    fn post_start(&mut self) {
        for ((fwd, _), e) in self.actions.iter().zip(&self.executors) {
            fwd.running.store(true, Ordering::Release);
            let _ = fwd.executor.set(*e);
        }
    }

    fn shutdown(&mut self) {
        for (fwd, _) in &self.actions {
            fwd.running.store(false, Ordering::Release);
            tracing::info!("{}", fwd.summary());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(json: serde_json::Value) -> Options {
        serde_json::from_value(json).expect("options")
    }

    fn known(t: &str) -> Result<(), String> {
        match t {
            "pb:A" | "pb:B" => Ok(()),
            other => Err(format!("msg_type '{other}' is in no type support package")),
        }
    }

    fn action(name: &str, topics: serde_json::Value) -> serde_json::Value {
        serde_json::json!({"name": name, "options": {"executor": "e", "topic_meta_list": topics}})
    }

    #[test]
    fn a_valid_plan_lists_each_action_with_its_routes() {
        let o = options(serde_json::json!({"proxy_actions": [
            action("one", serde_json::json!([
                {"sub_topic_name": "in", "pub_topic_name": ["out1", "out2"], "msg_type": "pb:A"},
                {"sub_topic_name": "in", "pub_topic_name": ["out1"], "msg_type": "pb:B"},
            ])),
        ]}));
        let p = plan(&o, known).expect("plan");
        assert_eq!(p.actions.len(), 1);
        let route = |msg_type: &str, to: &[&str]| Route {
            sub: "in".into(),
            msg_type: msg_type.into(),
            to: to.iter().map(|t| t.to_string()).collect(),
        };
        assert_eq!(
            p.actions[0],
            PlannedAction {
                name: "one".into(),
                executor: "e".into(),
                routes: vec![route("pb:A", &["out1", "out2"]), route("pb:B", &["out1"])],
            }
        );
        assert!(p.warnings.is_empty());
    }

    #[test]
    fn each_mistake_is_refused_with_its_place() {
        let cases = [
            (
                serde_json::json!([action("a", serde_json::json!([])), action("a", serde_json::json!([]))]),
                "proxy_actions[1] ('a'): the name is used by an earlier action",
            ),
            (
                serde_json::json!([{"name": "a", "options": {}}]),
                "proxy_actions[0] ('a'): options.executor is required",
            ),
            (
                serde_json::json!([action("a", serde_json::json!([{"sub_topic_name": "in", "pub_topic_name": ["o"], "msg_type": "pb:C"}]))]),
                "proxy_actions[0] ('a'): topic_meta_list[0].msg_type 'pb:C' is in no type support package",
            ),
            (
                serde_json::json!([action("a", serde_json::json!([{"sub_topic_name": "in", "pub_topic_name": [], "msg_type": "pb:A"}]))]),
                "proxy_actions[0] ('a'): topic_meta_list[0].pub_topic_name is empty",
            ),
            (
                serde_json::json!([
                    action("a", serde_json::json!([{"sub_topic_name": "in", "pub_topic_name": ["o"], "msg_type": "pb:A"}])),
                    action("b", serde_json::json!([{"sub_topic_name": "in", "pub_topic_name": ["p"], "msg_type": "pb:A"}])),
                ]),
                "proxy_actions[1] ('b'): topic_meta_list[0]: topic 'in' with type 'pb:A' is subscribed twice",
            ),
            (
                serde_json::json!([action("a", serde_json::json!([
                    {"sub_topic_name": "in", "pub_topic_name": ["o"], "msg_type": "pb:A"},
                    {"sub_topic_name": "in2", "pub_topic_name": ["p", "o"], "msg_type": "pb:A"},
                ]))]),
                "proxy_actions[0] ('a'): topic_meta_list[1].pub_topic_name[1]: topic 'o' with type 'pb:A' is published twice",
            ),
            (
                serde_json::json!([action("", serde_json::json!([]))]),
                "proxy_actions[0].name is empty",
            ),
        ];
        for (actions, expected) in cases {
            let o = options(serde_json::json!({ "proxy_actions": actions }));
            let err = plan(&o, known).expect_err(expected);
            assert!(err.starts_with(expected), "{err}\nexpected: {expected}");
        }
    }

    #[test]
    fn a_topic_forwarded_to_itself_is_warned_about() {
        let o = options(
            serde_json::json!({"proxy_actions": [action("a", serde_json::json!([
                {"sub_topic_name": "t", "pub_topic_name": ["t"], "msg_type": "pb:A"},
            ]))]}),
        );
        let p = plan(&o, known).expect("plan");
        assert_eq!(p.warnings.len(), 1);
        assert!(
            p.warnings[0].contains("topic 't' is forwarded to itself"),
            "{:?}",
            p.warnings
        );
    }

    #[test]
    fn unknown_keys_are_refused() {
        let o: Result<Options, _> = serde_json::from_value(serde_json::json!({"proxy_action": []}));
        assert!(o
            .unwrap_err()
            .to_string()
            .contains("unknown field `proxy_action`"));
    }
}
