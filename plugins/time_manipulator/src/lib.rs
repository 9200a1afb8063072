//! `time_manipulator_plugin` (`libaimrt_time_manipulator_plugin.so`): the executor type
//! `time_manipulator` — a timing wheel on time that can be sped up, slowed down and paused —
//! and `aimrt.protocols.time_manipulator_plugin.TimeManipulatorService`, which controls it
//! through any RPC backend (e.g. `http` of `net_plugin`).
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: time_manipulator_plugin
//!         path: ./target/debug/libaimrt_time_manipulator_plugin.so
//!         options:
//!           service_name: ""   # replaces the service part of the function names
//!   executor:
//!     executors:
//!       - name: real_work_thread_pool
//!         type: asio_thread
//!       - name: time_schedule_executor
//!         type: time_manipulator
//!         options: {bind_executor: real_work_thread_pool, dt_us: 1000, init_ratio: 2.0}
//! ```
//!
//! The service's functions are `pb:/<service>/SetTimeRatio`, `…/Pause` and
//! `…/GetTimeRatio`, JSON in and out, answering `{"time_ratio": …, "code": …, "msg": …}`
//! as AimRT does: code 0 on success, 1 `INVALID_EXECUTOR_NAME`, and (aimrt-rs) 2
//! `INVALID_TIME_RATIO` for a ratio that is not finite or above 1e6.
#![deny(unsafe_code)]

mod service;

use std::collections::BTreeMap;
use std::sync::{Arc, RwLock};

use aimrt_plugin_api::rpc::ServiceOptions;
use aimrt_plugin_api::{Error, Executor, Plugin, PluginOptions, Registrar};
use aimrt_std_executors::{create_time_manipulator, TimeManipulator};

use crate::service::Method;

/// The proto service name AimRT registers (the plugin option `service_name` replaces it).
pub(crate) const DEFAULT_SERVICE: &str =
    "aimrt.protocols.time_manipulator_plugin.TimeManipulatorService";

/// Every `time_manipulator` executor this plugin built, by name.
pub(crate) type Registry = Arc<RwLock<BTreeMap<String, Arc<TimeManipulator>>>>;

#[derive(Default)]
struct TimeManipulatorPlugin {
    registry: Registry,
}

impl Plugin for TimeManipulatorPlugin {
    fn name(&self) -> &str {
        "time_manipulator_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: ServiceOptions = registrar.read_options(options)?;
        let service = o.service(DEFAULT_SERVICE);
        let registry = self.registry.clone();
        registrar.register_executor_type("time_manipulator", &["bind_executor"], move |args| {
            let exec = create_time_manipulator(args)?;
            registry
                .write()
                .unwrap_or_else(|e| e.into_inner())
                .insert(exec.name().to_owned(), exec.clone());
            Ok(exec)
        })?;
        for method in Method::ALL {
            let registry = self.registry.clone();
            registrar.register_service(
                &format!("pb:/{service}/{}", method.name()),
                move |format, request| service::handle(method, &registry, format, request),
            )?;
        }
        Ok(())
    }
}

fn plugin() -> Box<dyn Plugin> {
    Box::new(TimeManipulatorPlugin::default())
}

aimrt_plugin_api::export_plugin!(plugin);
