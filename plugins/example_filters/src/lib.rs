//! An example plugin with channel filters (ABI 1.7; AimRT's `RegisterPublishFilter` /
//! `RegisterSubscribeFilter`), exported from `libexample_filters_plugin.so`. A topic runs
//! a filter when its rule in `aimrt.channel.pub_topics_options` or `sub_topics_options`
//! lists it in `enable_filters` (`config/channel_filter_plugin.yaml`, docs/channels.md):
//!
//! - `trace_id` (publish): sets the context key `trace-id` to `<module>-<n>` on a message
//!   that has none, `n` counting the messages this filter stamped;
//! - `sample` (publish): passes one message in `sample.keep_one_in` on and holds the
//!   others back (the runtime counts them as `filtered` in the topic's statistics);
//! - `time_cost` (subscribe): runs the subscriber, then logs how long it took.
//!
//! And RPC filters (ABI 1.9; AimRT's `RegisterClientFilter` / `RegisterServerFilter`),
//! listed in `enable_filters` of `aimrt.rpc.clients_options` / `servers_options`
//! (`config/rpc_filter_plugin.yaml`, docs/rpc.md):
//!
//! - `trace_id` (client): sets `trace-id` to `<module>-<n>` on a call that has none, and
//!   logs the call's status when it is answered;
//! - `require_trace_id` (server): answers a call without `trace-id` with
//!   `SVR_HANDLE_FAILED` and passes the others on to the service.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: example_filters
//!         path: ./target/debug/libexample_filters_plugin.so
//!         options:
//!           sample:
//!             keep_one_in: 2
//! ```
#![deny(unsafe_code)]

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use aimrt_plugin_api::channel::{FilterSide, Next, Publication};
use aimrt_plugin_api::rpc::{CallFilterSide, CallNext, FilterCall, RpcStatus};
use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar};
use serde::Deserialize;

#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Sample {
    #[serde(default = "one")]
    keep_one_in: u64,
}

fn one() -> u64 {
    1
}

#[derive(Debug, Default, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    sample: Option<Sample>,
}

struct ExampleFilters;

impl Plugin for ExampleFilters {
    fn name(&self) -> &str {
        "example_filters"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: Options = registrar.read_options(options)?;
        let keep_one_in = o.sample.map_or(1, |s| s.keep_one_in);
        if keep_one_in == 0 {
            return Err(options.invalid(
                "sample.keep_one_in is 0; give 1 to pass every message on, or n to pass one in n",
            ));
        }

        let stamped = AtomicU64::new(0);
        registrar.register_channel_filter(
            "trace_id",
            FilterSide::Publish,
            move |msg: &Publication<'_>, next: Next<'_>| {
                if msg.get("trace-id").is_some() {
                    return next.pass();
                }
                let n = stamped.fetch_add(1, Ordering::Relaxed) + 1;
                let mut ctx = next.context();
                ctx.set("trace-id", &format!("{}-{n}", msg.module()));
                next.pass_with(&ctx)
            },
        )?;

        let seen = AtomicU64::new(0);
        registrar.register_channel_filter(
            "sample",
            FilterSide::Publish,
            move |_: &Publication<'_>, next: Next<'_>| {
                let n = seen.fetch_add(1, Ordering::Relaxed);
                if n % keep_one_in == 0 {
                    next.pass()
                } else {
                    Ok(())
                }
            },
        )?;

        registrar.register_channel_filter(
            "time_cost",
            FilterSide::Subscribe,
            |msg: &Publication<'_>, next: Next<'_>| {
                let began = Instant::now();
                let result = next.pass();
                tracing::info!(
                    "time_cost: topic '{}', subscriber of module '{}': {} µs",
                    msg.topic(),
                    msg.module(),
                    began.elapsed().as_micros()
                );
                result
            },
        )?;
        register_rpc_filters(registrar)
    }
}

/// The RPC filters (ABI 1.9).
fn register_rpc_filters(registrar: &mut Registrar<'_>) -> Result<(), Error> {
    let stamped = AtomicU64::new(0);
    registrar.register_rpc_filter(
        "trace_id",
        CallFilterSide::Client,
        move |call: &FilterCall<'_>, next: CallNext<'_>| {
            let mut ctx = next.context();
            let trace_id = match call.get("trace-id") {
                Some(id) => id.to_owned(),
                None => {
                    let n = stamped.fetch_add(1, Ordering::Relaxed) + 1;
                    let id = format!("{}-{n}", call.module());
                    ctx.set_meta("trace-id", &id);
                    id
                }
            };
            let func = call.func().to_owned();
            next.on_reply(move |reply| {
                tracing::info!(
                    "trace_id: call of '{func}' with trace-id {trace_id} answered {}",
                    reply.status()
                )
            })
            .pass_with(&ctx)
        },
    )?;
    registrar.register_rpc_filter(
        "require_trace_id",
        CallFilterSide::Server,
        |call: &FilterCall<'_>, next: CallNext<'_>| match call.get("trace-id") {
            Some(_) => next.pass(),
            None => next.answer(
                RpcStatus::SVR_HANDLE_FAILED,
                "the call has no trace-id in its context",
            ),
        },
    )?;
    Ok(())
}

fn plugin() -> Box<dyn Plugin> {
    Box::new(ExampleFilters)
}

aimrt_plugin_api::export_plugin!(plugin);
