//! `parameter_plugin` (`libaimrt_parameter_plugin.so`):
//! `aimrt.protocols.parameter_plugin.ParameterService`, which reads and writes the modules'
//! parameters while the process runs, through any RPC backend (e.g. `http` of
//! `net_plugin`), in `pb` and `json`.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: parameter_plugin
//!         path: ./target/debug/libaimrt_parameter_plugin.so
//!         options:
//!           service_name: ""   # replaces the service part of the function names
//! ```
//!
//! `Set`, `Get` and `List` act on one module's parameters; `Dump` answers those of the
//! modules asked for (every module for none) and `Load` sets many at once, all or none.
//! An empty value removes the key (the service has no `Remove`), and `Get` of a key that
//! is not set answers an empty value, as AimRT. Code 0 is success; 1 `INVALID_MODULE_NAME`
//! names a module that does not exist, and nothing is changed.
#![deny(unsafe_code)]

use std::collections::BTreeMap;

use aimrt_plugin_api::rpc::{serve_message, ServiceOptions};
use aimrt_plugin_api::{Error, ParameterRef, Plugin, PluginOptions, Registrar, RuntimeControl};
use aimrt_protocols::parameter_plugin as pb;

/// The proto service name AimRT registers (the plugin option `service_name` replaces it).
const DEFAULT_SERVICE: &str = "aimrt.protocols.parameter_plugin.ParameterService";

const INVALID_MODULE_NAME: u32 = 1;

/// `(code, msg)` of a refusal.
type Refusal = (u32, String);

/// The parameters of every module named in `names`, or the refusal that names those that
/// do not exist.
fn stores<'a>(
    control: &RuntimeControl,
    names: impl IntoIterator<Item = &'a str>,
) -> Result<Vec<(&'a str, ParameterRef)>, Refusal> {
    let mut found = Vec::new();
    let mut unknown = Vec::new();
    for name in names {
        match control.module_parameters(name) {
            Some(p) => found.push((name, p)),
            None => unknown.push(name),
        }
    }
    if unknown.is_empty() {
        return Ok(found);
    }
    let modules = control.modules();
    let known: Vec<&str> = modules.iter().map(String::as_str).collect();
    Err((
        INVALID_MODULE_NAME,
        format!(
            "INVALID_MODULE_NAME: {}",
            aimrt_plugin_api::__private::no_such("module", &unknown, &known)
        ),
    ))
}

/// The parameters of module `name`.
fn store(control: &RuntimeControl, name: &str) -> Result<ParameterRef, Refusal> {
    stores(control, [name]).map(|mut v| v.remove(0).1)
}

/// Sets `key` to `value`; an empty value removes it.
fn put(params: &ParameterRef, key: &str, value: &str) {
    if value.is_empty() {
        params.remove(key);
    } else {
        params.set(key, value);
    }
}

fn set(control: &RuntimeControl, req: pb::SetParameterReq) -> pb::SetParameterRsp {
    match store(control, &req.module_name) {
        Ok(p) => {
            put(&p, &req.parameter_key, &req.parameter_value);
            pb::SetParameterRsp::default()
        }
        Err((code, msg)) => pb::SetParameterRsp {
            code: code.into(),
            msg,
        },
    }
}

fn get(control: &RuntimeControl, req: pb::GetParameterReq) -> pb::GetParameterRsp {
    match store(control, &req.module_name) {
        Ok(p) => pb::GetParameterRsp {
            parameter_value: p.get(&req.parameter_key).unwrap_or_default(),
            ..Default::default()
        },
        Err((code, msg)) => pb::GetParameterRsp {
            code,
            msg,
            ..Default::default()
        },
    }
}

fn list(control: &RuntimeControl, req: pb::ListParameterReq) -> pb::ListParameterRsp {
    match store(control, &req.module_name) {
        Ok(p) => pb::ListParameterRsp {
            parameter_keys: p.keys(),
            ..Default::default()
        },
        Err((code, msg)) => pb::ListParameterRsp {
            code,
            msg,
            ..Default::default()
        },
    }
}

fn dump(control: &RuntimeControl, req: pb::DumpParameterReq) -> pb::DumpParameterRsp {
    let every;
    let names: Vec<&str> = if req.module_names.is_empty() {
        every = control.modules();
        every.iter().map(String::as_str).collect()
    } else {
        req.module_names.iter().map(String::as_str).collect()
    };
    match stores(control, names) {
        Ok(found) => pb::DumpParameterRsp {
            module_parameter_map: found
                .into_iter()
                .map(|(name, p)| {
                    let value = p
                        .keys()
                        .into_iter()
                        .filter_map(|k| p.get(&k).map(|v| (k, v)))
                        .collect();
                    (name.to_owned(), pb::ParameterMap { value })
                })
                .collect(),
            ..Default::default()
        },
        Err((code, msg)) => pb::DumpParameterRsp {
            code,
            msg,
            ..Default::default()
        },
    }
}

fn load(control: &RuntimeControl, req: pb::LoadParameterReq) -> pb::LoadParameterRsp {
    let by_name: BTreeMap<&str, &pb::ParameterMap> = req
        .module_parameter_map
        .iter()
        .map(|(k, v)| (k.as_str(), v))
        .collect();
    match stores(control, by_name.keys().copied()) {
        Ok(found) => {
            for (name, p) in found {
                let values: BTreeMap<&String, &String> = by_name[name].value.iter().collect();
                for (k, v) in values {
                    put(&p, k, v);
                }
            }
            pb::LoadParameterRsp::default()
        }
        Err((code, msg)) => pb::LoadParameterRsp { code, msg },
    }
}

#[derive(Default)]
struct ParameterPlugin;

impl Plugin for ParameterPlugin {
    fn name(&self) -> &str {
        "parameter_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: ServiceOptions = registrar.read_options(options)?;
        let service = o.service(DEFAULT_SERVICE);
        let control = registrar.control()?;
        type Handler =
            fn(&RuntimeControl, &str, &[u8]) -> Result<Vec<u8>, aimrt_plugin_api::ServiceError>;
        let methods: [(&str, Handler); 5] = [
            ("Set", |c, f, b| serve_message(f, b, |r| set(c, r))),
            ("Get", |c, f, b| serve_message(f, b, |r| get(c, r))),
            ("List", |c, f, b| serve_message(f, b, |r| list(c, r))),
            ("Dump", |c, f, b| serve_message(f, b, |r| dump(c, r))),
            ("Load", |c, f, b| serve_message(f, b, |r| load(c, r))),
        ];
        for (method, handler) in methods {
            registrar.register_service(&format!("pb:/{service}/{method}"), move |f, b| {
                handler(&control, f, b)
            })?;
        }
        Ok(())
    }
}

fn plugin() -> Box<dyn Plugin> {
    Box::new(ParameterPlugin)
}

aimrt_plugin_api::export_plugin!(plugin);
