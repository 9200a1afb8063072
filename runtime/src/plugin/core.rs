//! A plugin's own core (ABI 1.3): the channel handle through which a plugin subscribes and
//! publishes by type name, as AimRT's plugins do as module `core`. Plugins initialize
//! before the channel is configured, so what they register during `initialize` waits here
//! and is applied by [`PluginCore::bind`], before modules initialize.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use aimrt_plugin_api::channel::TopicStats;
use aimrt_plugin_api::ffi::{
    MetaPair, RawExecutor, RawLogger, RawMessage, RawSubscriber, TypeSupportVtable,
};
use aimrt_plugin_api::{CoreHost, ModuleInfo};

use crate::channel::{ChannelManager, ModuleChannel};

/// What a plugin registered before the channel existed.
enum Pending {
    Publish(String, &'static TypeSupportVtable),
    Subscribe(String, &'static TypeSupportVtable, RawSubscriber),
}

/// The channel and executors, once the runtime has them.
struct Bound {
    channel: ModuleChannel,
    executors: HashMap<String, RawExecutor>,
}

/// One plugin's core.
pub(crate) struct PluginCore {
    info: ModuleInfo,
    library: String,
    logger: RawLogger,
    pending: Mutex<Vec<Pending>>,
    bound: OnceLock<Bound>,
    started: Arc<AtomicBool>,
    /// The plugin's parameters (its own, as a module's).
    parameters: crate::parameter::Parameters,
}

impl PluginCore {
    pub(crate) fn new(plugin: &str, library: &str, logger: RawLogger) -> PluginCore {
        PluginCore {
            info: ModuleInfo::new(plugin),
            library: library.to_owned(),
            logger,
            pending: Mutex::default(),
            bound: OnceLock::new(),
            started: Arc::default(),
            parameters: Default::default(),
        }
    }

    /// Gives the core the channel and executors and applies what the plugin registered
    /// during `initialize`; the first failure names the topic and why.
    pub(crate) fn bind(
        &self,
        manager: &Arc<ChannelManager>,
        executors: &HashMap<String, RawExecutor>,
    ) -> Result<(), String> {
        let channel = ModuleChannel::new(
            manager.clone(),
            &self.info.name,
            &self.library,
            self.started.clone(),
        );
        let pending = std::mem::take(&mut *self.pending.lock().unwrap_or_else(|e| e.into_inner()));
        let _ = self.bound.set(Bound {
            channel,
            executors: executors.clone(),
        });
        let Some(b) = self.bound.get() else {
            return Err("the plugin's core is bound twice".into());
        };
        for p in pending {
            match p {
                Pending::Publish(topic, ts) => b.channel.register_publish_type(&topic, ts)?,
                Pending::Subscribe(topic, ts, sub) => b.channel.subscribe(&topic, ts, sub)?,
            }
        }
        Ok(())
    }

    /// Messages from other processes reach the plugin's subscriptions from now on.
    pub(crate) fn start(&self) {
        self.started.store(true, Ordering::Release);
    }
}

impl CoreHost for PluginCore {
    crate::parameter::serve_parameters!(parameters);
    fn info(&self) -> &ModuleInfo {
        &self.info
    }
    fn config_file_path(&self) -> &str {
        ""
    }
    fn config_json(&self) -> &str {
        "null"
    }
    fn executor(&self, name: &str) -> Option<RawExecutor> {
        self.bound.get()?.executors.get(name).copied()
    }
    fn logger(&self) -> RawLogger {
        self.logger
    }
    fn register_publish_type(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        match self.bound.get() {
            Some(b) => b.channel.register_publish_type(topic, ts),
            None => {
                self.pending
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .push(Pending::Publish(topic.to_owned(), ts));
                Ok(())
            }
        }
    }
    fn subscribe(
        &self,
        topic: &str,
        ts: &'static TypeSupportVtable,
        sub: RawSubscriber,
    ) -> Result<(), String> {
        match self.bound.get() {
            Some(b) => b.channel.subscribe(topic, ts, sub),
            None => {
                self.pending
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .push(Pending::Subscribe(topic.to_owned(), ts, sub));
                Ok(())
            }
        }
    }
    fn publish(&self, topic: &[u8], ctx: &[MetaPair<'_>], msg: RawMessage) -> Result<(), String> {
        match self.bound.get() {
            Some(b) => b.channel.publish(topic, ctx, msg),
            None => Err(format!(
                "plugin '{}' published on '{}' before the channel was configured; publish from start on",
                self.info.name,
                String::from_utf8_lossy(topic)
            )),
        }
    }
    fn topic_stats(&self, topic: &str) -> Option<TopicStats> {
        self.bound.get()?.channel.stats(topic)
    }
}
