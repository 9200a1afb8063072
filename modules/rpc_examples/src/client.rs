//! `NormalRpcSyncClientModule`, `NormalRpcAsyncClientModule`,
//! `NormalRpcFutureClientModule`, `NormalRpcCoClientModule`.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use aimrt_plugin_api::co::{block_on, block_on_timeout, schedule_after, AsyncScope};
use aimrt_plugin_api::rpc::{filter, RpcResult};
use aimrt_plugin_api::{CoreRef, Error, ExecutorRef, Module, ModuleInfo, RpcContext};
use aimrt_protocols::example::{ExampleServiceClient, GetFooDataReq, GetFooDataRsp};

use crate::to_json;

/// How the client calls.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// Blocks the loop's thread until the answer (AimRT's sync proxy).
    Sync,
    /// Hands a callback and goes on (AimRT's async proxy).
    Async,
    /// Takes a future and waits on it (AimRT's future proxy).
    Future,
    /// Awaits the call inside the async loop (AimRT's co proxy).
    Co,
}

/// Calls `GetFooData` with `"hello world foo, count <n>"` every `1 / rpc_frq` seconds from
/// an async loop on `work_thread_pool`, with a 3 s timeout, and logs the answer as
/// AimRT's example does. Config: `rpc_frq` (calls per second), `service_name` (AimRT's),
/// `serialization_type` (ours: `pb` or `json`, the format calls cross libraries in).
#[derive(Debug)]
pub struct ClientModule {
    style: Style,
    setup: Option<Setup>,
    running: Option<Running>,
}

#[derive(Debug)]
struct Setup {
    executor: ExecutorRef,
    client: ExampleServiceClient,
    period: Duration,
    /// `serialization_type` (ours): the format calls cross libraries in (default `pb`).
    format: Option<String>,
}

#[derive(Debug)]
struct Running {
    scope: AsyncScope,
    run: Arc<AtomicBool>,
}

impl ClientModule {
    /// A client of `style`.
    pub fn new(style: Style) -> ClientModule {
        ClientModule {
            style,
            setup: None,
            running: None,
        }
    }
}

fn log_result(result: &RpcResult<GetFooDataRsp>) {
    match result {
        Ok(rsp) => tracing::info!(
            "Client get rpc ret, status: {}, rsp: {}",
            aimrt_plugin_api::RpcStatus::OK,
            to_json(&**rsp)
        ),
        Err(status) => tracing::warn!("Client get rpc error ret, status: {status}"),
    }
}

impl Module for ClientModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new(match self.style {
            Style::Sync => "NormalRpcSyncClientModule",
            Style::Async => "NormalRpcAsyncClientModule",
            Style::Future => "NormalRpcFutureClientModule",
            Style::Co => "NormalRpcCoClientModule",
        })
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: serde_json::Value = core.config()?;
        let rpc_frq = cfg
            .get("rpc_frq")
            .and_then(serde_json::Value::as_f64)
            .unwrap_or(1.0);
        if !(rpc_frq.is_finite() && rpc_frq > 0.0) {
            return Err(Error::msg(format!(
                "rpc_frq is {rpc_frq}; it must be a positive number of calls per second"
            )));
        }
        let executor = core.executor("work_thread_pool")?;
        if !executor.supports_timer_schedule() {
            return Err(Error::msg(
                "executor 'work_thread_pool' has no timers; make it an asio_thread or time_wheel",
            ));
        }
        let rpc = core.rpc()?;
        let client = match crate::service_name(&cfg, "service_name")? {
            Some(name) => ExampleServiceClient::register_as(&rpc, &name),
            None => ExampleServiceClient::register(&rpc),
        }
        .map_err(|e| Error::msg(format!("RegisterClientFunc failed: {e}")))?;
        let mut client = client;
        if self.style == Style::Co {
            // As AimRT's co client: a debug-log filter, then a time-cost filter (the
            // outermost).
            let get_foo = client.get_foo_data_mut();
            get_foo.add_filter(filter(|ctx, req| {
                tracing::info!(
                    "Client start new rpc call. context: {ctx}, req: {}",
                    req.to_json().unwrap_or_default()
                );
                Box::new(|_, _| {})
            }));
            get_foo.add_filter(filter(|_, _| {
                let begin = Instant::now();
                Box::new(move |_, _| {
                    tracing::info!("Client rpc time cost {} us", begin.elapsed().as_micros())
                })
            }));
        }
        self.setup = Some(Setup {
            executor,
            client,
            period: Duration::from_secs_f64(1.0 / rpc_frq),
            format: cfg
                .get("serialization_type")
                .and_then(serde_json::Value::as_str)
                .map(str::to_owned),
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
        let style = self.style;
        let exec = setup.executor;
        running.scope.spawn(exec, async move {
            tracing::info!("Start MainLoop.");
            let mut count: u64 = 0;
            while run.load(Ordering::SeqCst) {
                schedule_after(&exec, setup.period).await?;
                if !run.load(Ordering::SeqCst) {
                    break;
                }
                count += 1;
                tracing::info!("Loop count : {count} -------------------------");
                let req = GetFooDataReq {
                    msg: format!("hello world foo, count {count}"),
                };
                let get_foo = setup.client.get_foo_data();
                let mut ctx = get_foo.new_context();
                ctx.set_timeout(Some(Duration::from_secs(3)));
                if let Some(f) = &setup.format {
                    ctx.set_serialization_type(f);
                }
                match style {
                    Style::Co => {
                        // The filters (set in initialize) log the start and the time cost.
                        let result = get_foo.call_async(&mut ctx, req).await;
                        log_result(&result);
                    }
                    Style::Sync => {
                        tracing::info!("Client start new rpc call. req: {}", to_json(&req));
                        log_result(&get_foo.call(&mut ctx, req));
                    }
                    Style::Future => {
                        tracing::info!("Client start new rpc call. req: {}", to_json(&req));
                        let future = get_foo.call_async(&mut ctx, req);
                        log_result(&block_on(future));
                    }
                    Style::Async => {
                        tracing::info!("Client start new rpc call. req: {}", to_json(&req));
                        get_foo.call_then(ctx, req, |_ctx: RpcContext, result| log_result(&result));
                    }
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
