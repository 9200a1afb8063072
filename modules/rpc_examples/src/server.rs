//! `NormalRpcSyncServerModule`, `NormalRpcAsyncServerModule`, `NormalRpcCoServerModule`.

use std::sync::Arc;

use std::time::Instant;

use aimrt_plugin_api::rpc::{filter, Reply, RpcFilter};
use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo, RpcContext, RpcStatus};
use aimrt_protocols::example::{
    ExampleServiceAsync, ExampleServiceCo, ExampleServiceSync, GetBarDataReq, GetBarDataRsp,
    GetFooDataReq, GetFooDataRsp,
};

use crate::to_json;

/// How the server answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Style {
    /// `ExampleServiceSync`: returns the response.
    Sync,
    /// `ExampleServiceAsync`: answers through the reply handle.
    Async,
    /// `ExampleServiceCo`: `async fn`.
    Co,
}

/// Serves `ExampleService` (renamed by `service_name`): `GetFooData` and `GetBarData`
/// answer `"echo " + msg`.
#[derive(Debug)]
pub struct ServerModule {
    style: Style,
}

impl ServerModule {
    /// A server of `style`.
    pub fn new(style: Style) -> ServerModule {
        ServerModule { style }
    }
}

/// The service, in every style.
struct Echo;

fn foo(ctx: &RpcContext, req: &GetFooDataReq) -> GetFooDataRsp {
    let rsp = GetFooDataRsp {
        msg: format!("echo {}", req.msg),
        ..Default::default()
    };
    tracing::info!(
        "Server handle new rpc call. context: {ctx}, req: {}, return rsp: {}",
        to_json(req),
        to_json(&rsp)
    );
    rsp
}

fn bar(ctx: &RpcContext, req: &GetBarDataReq) -> GetBarDataRsp {
    let rsp = GetBarDataRsp {
        msg: format!("echo {}", req.msg),
        ..Default::default()
    };
    tracing::info!(
        "Server handle new rpc call. context: {ctx}, req: {}, return rsp: {}",
        to_json(req),
        to_json(&rsp)
    );
    rsp
}

impl ExampleServiceSync for Echo {
    fn get_foo_data(
        &self,
        ctx: &RpcContext,
        req: &GetFooDataReq,
    ) -> Result<GetFooDataRsp, RpcStatus> {
        Ok(foo(ctx, req))
    }
    fn get_bar_data(
        &self,
        ctx: &RpcContext,
        req: &GetBarDataReq,
    ) -> Result<GetBarDataRsp, RpcStatus> {
        Ok(bar(ctx, req))
    }
}

impl ExampleServiceAsync for Echo {
    fn get_foo_data(&self, ctx: RpcContext, req: Arc<GetFooDataReq>, reply: Reply<GetFooDataRsp>) {
        reply.send(Ok(foo(&ctx, &req)));
    }
    fn get_bar_data(&self, ctx: RpcContext, req: Arc<GetBarDataReq>, reply: Reply<GetBarDataRsp>) {
        reply.send(Ok(bar(&ctx, &req)));
    }
}

impl ExampleServiceCo for Echo {
    /// As AimRT's co server: a debug-log filter, then a time-cost filter (the outermost).
    fn filters(&self) -> Vec<RpcFilter> {
        vec![
            filter(|ctx, req| {
                tracing::info!(
                    "Svr get new rpc call. context: {ctx}, req: {}",
                    req.to_json().unwrap_or_default()
                );
                Box::new(|_, result| match result {
                    Ok(rsp) => tracing::info!(
                        "Svr handle rpc completed, status: {}, rsp: {}",
                        RpcStatus::OK,
                        rsp.to_json().unwrap_or_default()
                    ),
                    Err(status) => tracing::info!("Svr handle rpc completed, status: {status}"),
                })
            }),
            filter(|_, _| {
                let begin = Instant::now();
                Box::new(move |_, _| {
                    tracing::info!("Svr rpc time cost {} us", begin.elapsed().as_micros())
                })
            }),
        ]
    }

    async fn get_foo_data(
        &self,
        ctx: RpcContext,
        req: Arc<GetFooDataReq>,
    ) -> Result<GetFooDataRsp, RpcStatus> {
        Ok(foo(&ctx, &req))
    }
    async fn get_bar_data(
        &self,
        ctx: RpcContext,
        req: Arc<GetBarDataReq>,
    ) -> Result<GetBarDataRsp, RpcStatus> {
        Ok(bar(&ctx, &req))
    }
}

impl Module for ServerModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new(match self.style {
            Style::Sync => "NormalRpcSyncServerModule",
            Style::Async => "NormalRpcAsyncServerModule",
            Style::Co => "NormalRpcCoServerModule",
        })
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: serde_json::Value = core.config()?;
        let name = crate::service_name(&cfg, "service_name")?;
        let rpc = core.rpc()?;
        let echo = Arc::new(Echo);
        let registered = match (self.style, name) {
            (Style::Sync, None) => ExampleServiceSync::register(echo, &rpc),
            (Style::Sync, Some(n)) => ExampleServiceSync::register_as(echo, &rpc, &n),
            (Style::Async, None) => ExampleServiceAsync::register(echo, &rpc),
            (Style::Async, Some(n)) => ExampleServiceAsync::register_as(echo, &rpc, &n),
            (Style::Co, None) => ExampleServiceCo::register(echo, &rpc),
            (Style::Co, Some(n)) => ExampleServiceCo::register_as(echo, &rpc, &n),
        };
        registered.map_err(|e| Error::msg(format!("Register service failed: {e}")))?;
        tracing::info!("Register service succeeded.");
        tracing::info!("Init succeeded.");
        Ok(())
    }

    fn start(&mut self) -> Result<(), Error> {
        tracing::info!("Start succeeded.");
        Ok(())
    }

    fn shutdown(&mut self) {
        tracing::info!("Shutdown succeeded.");
    }
}
