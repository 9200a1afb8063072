//! `NormalPublisherModule`.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::channel::{Publisher, KEY_SERIALIZATION_TYPE};
use aimrt_plugin_api::co::{block_on_timeout, schedule_after, AsyncScope};
use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo};
use serde::Deserialize;

use crate::{to_json, ExampleEventMsg};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Config {
    topic_name: String,
    /// Messages per second.
    channel_frq: f64,
    /// The format messages cross libraries in (default: the type's first, `pb`).
    #[serde(default)]
    serialization_type: Option<String>,
    /// User keys set in every publish context.
    #[serde(default)]
    context_meta: BTreeMap<String, String>,
    /// Pads `msg` with `.` to this many bytes (for large-message runs; logged by size).
    #[serde(default)]
    msg_size: Option<usize>,
}

/// Publishes `ExampleEventMsg { msg: "count: N", num: N }` on `topic_name`,
/// `channel_frq` times a second, from an async loop on the `work_thread_pool` executor
/// (which must support timers), as AimRT's example.
#[derive(Debug, Default)]
pub struct NormalPublisherModule {
    running: Option<Running>,
    setup: Option<Setup>,
}

#[derive(Debug)]
struct Setup {
    executor: ExecutorRef,
    publisher: Publisher<ExampleEventMsg>,
    period: Duration,
    format: Option<String>,
    msg_size: usize,
}

#[derive(Debug)]
struct Running {
    scope: AsyncScope,
    run: Arc<AtomicBool>,
}

impl Module for NormalPublisherModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("NormalPublisherModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: Config = core.config()?;
        if !(cfg.channel_frq.is_finite() && cfg.channel_frq > 0.0) {
            return Err(Error::msg(format!(
                "channel_frq is {}; it must be a positive number of messages per second",
                cfg.channel_frq
            )));
        }
        let executor = core.executor("work_thread_pool")?;
        if !executor.supports_timer_schedule() {
            return Err(Error::msg(
                "executor 'work_thread_pool' has no timers; make it an asio_thread or time_wheel",
            ));
        }
        let mut publisher = core
            .channel()?
            .publisher::<ExampleEventMsg>(&cfg.topic_name)?;
        for (k, v) in &cfg.context_meta {
            publisher.set_default_meta(k, v);
        }
        self.setup = Some(Setup {
            executor,
            publisher,
            period: Duration::from_secs_f64(1.0 / cfg.channel_frq),
            format: cfg.serialization_type,
            msg_size: cfg.msg_size.unwrap_or(0),
        });
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        let Some(setup) = self.setup.take() else {
            return Ok(());
        };
        let running = Running {
            scope: AsyncScope::new(),
            run: Arc::new(AtomicBool::new(true)),
        };
        let run = running.run.clone();
        let exec = setup.executor;
        running.scope.spawn(exec, async move {
            tracing::info!("Start MainLoop.");
            let mut count: i32 = 0;
            while run.load(Ordering::SeqCst) {
                schedule_after(&exec, setup.period).await?;
                if !run.load(Ordering::SeqCst) {
                    break;
                }
                count += 1;
                tracing::info!("loop count : {count} -------------------------");
                let mut text = format!("count: {count}");
                if text.len() < setup.msg_size {
                    text.extend(std::iter::repeat_n('.', setup.msg_size - text.len()));
                }
                let msg = ExampleEventMsg {
                    msg: text,
                    num: count,
                };
                tracing::info!("Publish new pb event, data: {}", to_json(&msg));
                let mut ctx = setup.publisher.new_context(None);
                if let Some(f) = &setup.format {
                    ctx.set(KEY_SERIALIZATION_TYPE, f);
                }
                if let Err(e) = setup.publisher.publish_with(&mut ctx, msg) {
                    tracing::error!("Publish failed: {e}");
                }
            }
            tracing::info!("Exit MainLoop.");
            Ok::<_, Error>(())
        })?;
        self.running = Some(running);
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        if let Some(r) = self.running.take() {
            r.run.store(false, Ordering::SeqCst);
            if block_on_timeout(r.scope.complete(), Duration::from_secs(5)).is_none() {
                tracing::warn!("MainLoop did not end within 5 s.");
            }
        }
        tracing::info!("Shutdown succeeded.");
    }
}
