//! AimRT's `HelloWorldModule`, the first example: `libhelloworld_pkg.so` exports it for
//! `aimrt_main` (`config/helloworld.yaml`), and `helloworld_app` registers it in code
//! (`config/helloworld_app_mode.yaml`).
#![deny(unsafe_code)]

use std::collections::BTreeMap;

use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};

/// AimRT's `HelloWorldModule`: logs its lifecycle and every key of its config.
#[derive(Debug, Default)]
pub struct HelloWorldModule;

impl Module for HelloWorldModule {
    fn info(&self) -> ModuleInfo {
        ModuleInfo::new("HelloWorldModule")
    }

    fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
        tracing::info!("Init.");
        let cfg: BTreeMap<String, serde_json::Value> = core.config()?;
        for (k, v) in cfg {
            let v = v.as_str().map_or_else(|| v.to_string(), str::to_owned);
            tracing::info!("cfg [{k} : {v}]");
        }
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
