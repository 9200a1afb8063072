//! `NormalSubscriberModule`, `AsyncSubscriberModule` and `RelayModule`.

use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::channel::Context;
use aimrt_plugin_api::co::schedule_after;
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
use serde::Deserialize;

use crate::{to_json, ExampleEventMsg};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TopicConfig {
    topic_name: String,
}

/// Logs every `ExampleEventMsg` of `topic_name` with its context, as AimRT's example.
#[derive(Debug, Default)]
pub struct NormalSubscriberModule;

impl Module for NormalSubscriberModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("NormalSubscriberModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: TopicConfig = core.config()?;
        core.channel()?.subscriber(&cfg.topic_name).subscribe(
            |ctx: &Context, msg: Arc<ExampleEventMsg>| {
                tracing::info!("Receive new pb event, ctx: {ctx}, data: {}", to_json(&msg));
            },
        )?;
        tracing::info!("Init succeeded.");
        Ok(())
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct AsyncConfig {
    topic_name: String,
    /// The executor the handlers run on (must support timers: the handler waits on it).
    executor: String,
}

/// Handles each message of `topic_name` in an async task on `executor`: it waits 10 ms on
/// the executor's clock (a stand-in for async work that blocks no thread), then logs.
#[derive(Debug, Default)]
pub struct AsyncSubscriberModule;

impl Module for AsyncSubscriberModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("AsyncSubscriberModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: AsyncConfig = core.config()?;
        let exec = core.executor(&cfg.executor)?;
        core.channel()?
            .subscriber(&cfg.topic_name)
            .subscribe_async(
                &exec,
                move |ctx: Context, msg: Arc<ExampleEventMsg>| async move {
                    if let Err(e) = schedule_after(&exec, Duration::from_millis(10)).await {
                        tracing::error!("async handler stopped: {e}");
                        return;
                    }
                    tracing::info!(
                        "Async handled pb event, seq: {}, data: {}",
                        ctx.get("aimrt-pub_seq").unwrap_or("?"),
                        to_json(&msg)
                    );
                },
            )?;
        tracing::info!("Init succeeded.");
        Ok(())
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RelayConfig {
    sub_topic_name: String,
    pub_topic_name: String,
}

/// Republishes every message of `sub_topic_name` on `pub_topic_name`, with a publish
/// context made from the received one (`new_context(Some(&ctx))`): user keys travel
/// downstream, while `aimrt-pub_seq` and `aimrt-pub_ts` are the downstream topic's own.
#[derive(Debug, Default)]
pub struct RelayModule;

impl Module for RelayModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("RelayModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: RelayConfig = core.config()?;
        let channel = core.channel()?;
        let publisher = channel.publisher::<ExampleEventMsg>(&cfg.pub_topic_name)?;
        channel.subscriber(&cfg.sub_topic_name).subscribe(
            move |ctx: &Context, msg: Arc<ExampleEventMsg>| {
                let mut out = publisher.new_context(Some(ctx));
                tracing::info!(
                    "Relay pb event, upstream seq: {}, data: {}",
                    ctx.get("aimrt-pub_seq").unwrap_or("?"),
                    to_json(&msg)
                );
                if let Err(e) = publisher.publish_with(&mut out, msg) {
                    tracing::error!("Relay failed: {e}");
                }
            },
        )?;
        tracing::info!("Init succeeded.");
        Ok(())
    }
}
