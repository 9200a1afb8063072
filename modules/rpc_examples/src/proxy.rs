//! `ProxyRpcCoModule`.

use std::sync::Arc;
use std::time::Duration;

use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo, RpcContext, RpcStatus};
use aimrt_protocols::example::{
    ExampleServiceClient, ExampleServiceCo, GetBarDataReq, GetBarDataRsp, GetFooDataReq,
    GetFooDataRsp,
};

use crate::to_json;

/// Serves `ExampleService` under `service_name_for_server`; its `GetFooData` calls
/// `GetFooData` of `service_name_for_client` (3 s timeout) and answers what that answered.
#[derive(Debug, Default)]
pub struct ProxyRpcCoModule;

struct Proxy {
    client: ExampleServiceClient,
}

impl ExampleServiceCo for Proxy {
    async fn get_foo_data(
        &self,
        ctx: RpcContext,
        req: Arc<GetFooDataReq>,
    ) -> Result<GetFooDataRsp, RpcStatus> {
        let get_foo = self.client.get_foo_data();
        let mut call_ctx = get_foo.new_context();
        call_ctx.set_timeout(Some(Duration::from_secs(3)));
        let rsp = get_foo.call_async(&mut call_ctx, req.clone()).await?;
        let rsp = GetFooDataRsp {
            code: rsp.code,
            msg: rsp.msg.clone(),
            ..Default::default()
        };
        tracing::info!(
            " Server handle new rpc call. context: {ctx}, req: {}, return rsp: {}",
            to_json(&*req),
            to_json(&rsp)
        );
        Ok(rsp)
    }

    async fn get_bar_data(
        &self,
        ctx: RpcContext,
        req: Arc<GetBarDataReq>,
    ) -> Result<GetBarDataRsp, RpcStatus> {
        let rsp = GetBarDataRsp {
            msg: format!("echo {}", req.msg),
            ..Default::default()
        };
        tracing::info!(
            " Server handle new rpc call. context: {ctx}, req: {}, return rsp: {}",
            to_json(&*req),
            to_json(&rsp)
        );
        Ok(rsp)
    }
}

impl Module for ProxyRpcCoModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("ProxyRpcCoModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        let cfg: serde_json::Value = core.config()?;
        let rpc = core.rpc()?;
        let client = match crate::service_name(&cfg, "service_name_for_client")? {
            Some(name) => ExampleServiceClient::register_as(&rpc, &name),
            None => ExampleServiceClient::register(&rpc),
        }
        .map_err(|e| Error::msg(format!("RegisterClientFunc failed: {e}")))?;
        let proxy = Arc::new(Proxy { client });
        match crate::service_name(&cfg, "service_name_for_server")? {
            Some(name) => proxy.register_as(&rpc, &name),
            None => proxy.register(&rpc),
        }
        .map_err(|e| Error::msg(format!("Register service failed: {e}")))?;
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
