//! `zenoh_plugin`: the `zenoh` channel backend and the `zenoh` RPC backend, configured like
//! AimRT's zenoh_plugin, speaking its key expressions and payload layout ([`wire`]), on
//! the `zenoh` crate. This crate is the plugin as an rlib; `plugins/zenoh/so` exports it
//! from `libaimrt_zenoh_plugin.so`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: zenoh_plugin
//!         path: ./target/debug/libaimrt_zenoh_plugin.so
//!         options:
//!           native_cfg_path: ./config/zenoh_native_a.json5  # empty: zenoh's defaults
//!           limit_domain: room1                              # appended to every key
//!           shm_pool_size: 10485760                          # bytes, for shm_enabled
//!   channel:
//!     backends:
//!       - type: zenoh
//!         options:
//!           pub_topics_options:
//!             - {topic_name: "(.*)", shm_enabled: false}
//!   rpc:
//!     backends:
//!       - type: zenoh
//!         options:
//!           clients_options: [{func_name: "(.*)", shm_enabled: false}]
//!           servers_options: [{func_name: "(.*)", shm_enabled: false}]
//! ```
//!
//! Unlike AimRT, a native config that does not load, a session that does not open, or a
//! shared-memory pool that cannot be created is an error that stops start-up.
#![deny(unsafe_code)]

mod channel;
mod connect;
mod rpc;
mod sequence;
mod session;
pub mod wire;

use std::sync::{Arc, Mutex};

use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar};
use serde::Deserialize;

pub use crate::session::{load_native_config, shm_alloc, ZenohOptions};
use crate::session::{lock, Zenoh};

struct ZenohPlugin {
    zenoh: Mutex<Option<Opened>>,
}

/// The session and what the backends declared on it.
struct Opened {
    zenoh: Arc<Zenoh>,
    declared: [Arc<dyn Release>; 2],
}

/// What a backend declared on the session: released at the backend's shutdown, and again
/// (doing nothing the second time) at the plugin's, which also comes where the backend's
/// does not (a start-up that failed before the backend started). Publishing or calling
/// after it is refused and counted; with everything released, closing the session frees
/// all zenoh holds for it.
pub(crate) trait Release: Send + Sync {
    fn release(&self);
}

impl Plugin for ZenohPlugin {
    fn name(&self) -> &str {
        "zenoh_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        aimrt_plugin_api::rewrite_log_lines(session::zenoh_log_line);
        let o: ZenohOptions = registrar.read_options(options)?;
        let zenoh = Arc::new(Zenoh::open(o, options)?);
        let channel = channel::ZenohChannel::new(zenoh.clone());
        let rpc = rpc::ZenohRpc::new(zenoh.clone());
        *lock(&self.zenoh) = Some(Opened {
            zenoh,
            declared: [channel.declared(), rpc.declared()],
        });
        let registered = registrar
            .register_channel_backend(channel)
            .and_then(|()| registrar.register_rpc_backend(rpc));
        // A plugin that fails to initialize gets no shutdown: the session closes here.
        if registered.is_err() {
            self.shutdown();
        }
        registered
    }

    fn shutdown(&mut self) {
        let taken = lock(&self.zenoh).take();
        if let Some(opened) = taken {
            for d in &opened.declared {
                d.release();
            }
            opened.zenoh.close();
        }
    }
}

/// The plugin, as `libaimrt_zenoh_plugin.so` exports it (`plugins/zenoh/so`).
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(ZenohPlugin {
        zenoh: Mutex::new(None),
    })
}

/// `{func_name, shm_enabled}`: one entry of `clients_options` or `servers_options` (or of
/// `pub_topics_options`, converted from [`TopicShmRule`]).
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct ShmRule {
    func_name: String,
    #[serde(default)]
    shm_enabled: bool,
    /// A topic's `send_sequence` (not a key of RPC rules).
    #[serde(skip, default = "yes")]
    send_sequence: bool,
}

fn yes() -> bool {
    true
}

/// `pub_topics_options[i]` of the channel backend: AimRT's keys, and `send_sequence`, ours.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct TopicShmRule {
    topic_name: String,
    #[serde(default)]
    shm_enabled: bool,
    /// Whether each message carries zenoh's source info, from which subscribers count the
    /// messages zenoh lost on the way (docs/zenoh.md).
    #[serde(default = "yes")]
    send_sequence: bool,
}

impl From<TopicShmRule> for ShmRule {
    fn from(r: TopicShmRule) -> ShmRule {
        ShmRule {
            func_name: r.topic_name,
            shm_enabled: r.shm_enabled,
            send_sequence: r.send_sequence,
        }
    }
}

/// What the first rule matching a name says of it.
#[derive(Debug, Clone, Copy)]
struct RuleFlags {
    shm: bool,
    send_sequence: bool,
}

/// Compiled rules: the first whose pattern fully matches a name decides its flags.
#[derive(Debug, Default)]
struct ShmRules(Vec<(regex::Regex, RuleFlags)>);

impl ShmRules {
    /// Compiles `rules`; `list` and `key` name the option in errors.
    fn compile(rules: Vec<ShmRule>, where_: &str, list: &str, key: &str) -> Result<Self, Error> {
        let mut out = Vec::new();
        for (i, r) in rules.into_iter().enumerate() {
            let re = aimrt_plugin_api::whole_match(&r.func_name).map_err(|e| Error::Options {
                what: format!("zenoh backend options at {where_}"),
                message: format!(
                    "{list}[{i}].{key} '{}' is not a valid regular expression: {e}",
                    r.func_name
                ),
            })?;
            let flags = RuleFlags {
                shm: r.shm_enabled,
                send_sequence: r.send_sequence,
            };
            out.push((re, flags));
        }
        Ok(ShmRules(out))
    }

    /// What the first rule matching any of `names` says (`None`: no rule matches).
    fn first(&self, names: &[&str]) -> Option<RuleFlags> {
        self.0
            .iter()
            .find(|(re, _)| names.iter().any(|n| re.is_match(n)))
            .map(|(_, flags)| *flags)
    }

    /// Whether the first rule matching any of `names` enables shared memory.
    fn shm(&self, names: &[&str]) -> bool {
        self.first(names).is_some_and(|f| f.shm)
    }
}
