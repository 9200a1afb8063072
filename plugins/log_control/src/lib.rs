//! `log_control_plugin` (`libaimrt_log_control_plugin.so`):
//! `aimrt.protocols.log_control_plugin.LogControlService`, which reads and sets the
//! loggers' levels while the process runs, through any RPC backend (e.g. `http` of
//! `net_plugin`), in `pb` and `json`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: log_control_plugin
//!         path: ./target/debug/libaimrt_log_control_plugin.so
//!         options:
//!           service_name: ""   # replaces the service part of the function names
//! ```
//!
//! `GetModuleLogLevel` answers the levels of the loggers it is asked for (every logger for
//! an empty list); `SetModuleLogLevel` sets the levels of a map logger → level, all or
//! none. Code 0 is success; 1 `INVALID_MODULE_NAME` names a logger that does not exist, 2
//! `INVALID_LOG_LEVEL` (aimrt-rs) a level that is none of `Trace`, `Debug`, `Info`,
//! `Warn`, `Error`, `Fatal`, `Off` (any case). AimRT ignores unknown loggers.
#![deny(unsafe_code)]

use std::collections::BTreeMap;

use aimrt_plugin_api::rpc::{serve_message, ServiceOptions};
use aimrt_plugin_api::{Error, LogLevel, Plugin, PluginOptions, Registrar, RuntimeControl};
use aimrt_protocols::log_control_plugin as pb;

/// The proto service name AimRT registers (the plugin option `service_name` replaces it).
const DEFAULT_SERVICE: &str = "aimrt.protocols.log_control_plugin.LogControlService";

const INVALID_MODULE_NAME: u32 = 1;
const INVALID_LOG_LEVEL: u32 = 2;

/// `(code, msg)` of a refusal: the message starts with AimRT's code name.
fn refusal(code: u32, why: &str) -> (u32, String) {
    let name = match code {
        INVALID_MODULE_NAME => "INVALID_MODULE_NAME",
        _ => "INVALID_LOG_LEVEL",
    };
    (code, format!("{name}: {why}"))
}

/// The names of `asked` that are not loggers, as a refusal.
fn unknown_loggers<'a>(
    asked: impl Iterator<Item = &'a String>,
    levels: &BTreeMap<String, LogLevel>,
) -> Option<(u32, String)> {
    let unknown: Vec<&str> = asked
        .filter(|n| !levels.contains_key(*n))
        .map(String::as_str)
        .collect();
    let known: Vec<&str> = levels.keys().map(String::as_str).collect();
    (!unknown.is_empty()).then(|| {
        refusal(
            INVALID_MODULE_NAME,
            &aimrt_plugin_api::__private::no_such("logger", &unknown, &known),
        )
    })
}

/// `GetModuleLogLevel`: the levels asked for (every logger for none); the known ones also
/// when some are unknown, as AimRT.
fn get(control: &RuntimeControl, req: pb::GetModuleLogLevelReq) -> pb::GetModuleLogLevelRsp {
    let levels: BTreeMap<String, LogLevel> = control.log_levels().into_iter().collect();
    let mut rsp = pb::GetModuleLogLevelRsp::default();
    let wanted: Vec<&String> = if req.module_names.is_empty() {
        levels.keys().collect()
    } else {
        req.module_names.iter().collect()
    };
    for name in wanted {
        if let Some(level) = levels.get(name) {
            rsp.module_log_level_map
                .insert(name.clone(), level.name().to_owned());
        }
    }
    if let Some((code, msg)) = unknown_loggers(req.module_names.iter(), &levels) {
        rsp.code = code;
        rsp.msg = msg;
    }
    rsp
}

/// `SetModuleLogLevel`: every level of the map, or none when a logger or a level is
/// unknown.
fn set(control: &RuntimeControl, req: pb::SetModuleLogLevelReq) -> pb::SetModuleLogLevelRsp {
    let refused = |(code, msg): (u32, String)| pb::SetModuleLogLevelRsp { code, msg };
    let levels: BTreeMap<String, LogLevel> = control.log_levels().into_iter().collect();
    let asked: BTreeMap<&String, &String> = req.module_log_level_map.iter().collect();
    if let Some(r) = unknown_loggers(asked.keys().copied(), &levels) {
        return refused(r);
    }
    let mut parsed = Vec::with_capacity(asked.len());
    for (name, level) in asked {
        match level.parse::<LogLevel>() {
            Ok(l) => parsed.push((name, l)),
            Err(e) => return refused(refusal(INVALID_LOG_LEVEL, &format!("logger '{name}': {e}"))),
        }
    }
    for (name, level) in parsed {
        if let Err(e) = control.set_log_level(name, level) {
            return refused(refusal(INVALID_MODULE_NAME, &e.to_string()));
        }
    }
    pb::SetModuleLogLevelRsp::default()
}

#[derive(Default)]
struct LogControlPlugin;

impl Plugin for LogControlPlugin {
    fn name(&self) -> &str {
        "log_control_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: ServiceOptions = registrar.read_options(options)?;
        let service = o.service(DEFAULT_SERVICE);
        let control = registrar.control()?;
        registrar.register_service(
            &format!("pb:/{service}/GetModuleLogLevel"),
            move |format, bytes| serve_message(format, bytes, |r| get(&control, r)),
        )?;
        registrar.register_service(
            &format!("pb:/{service}/SetModuleLogLevel"),
            move |format, bytes| serve_message(format, bytes, |r| set(&control, r)),
        )
    }
}

fn plugin() -> Box<dyn Plugin> {
    Box::new(LogControlPlugin)
}

aimrt_plugin_api::export_plugin!(plugin);
