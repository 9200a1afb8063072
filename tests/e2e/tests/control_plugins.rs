//! End-to-end: `log_control_plugin` and `parameter_plugin` loaded by the real
//! `aimrt_main` from `config/`, called over real HTTP in AimRT's JSON. Each test listens on
//! a port of its own (port 0, read back from the log).

use std::time::Duration;

use aimrt_e2e::{http, repo_config, with_port, Running};
use serde_json::{json, Value};

const LOG_CONTROL: &str = "/rpc/aimrt.protocols.log_control_plugin.LogControlService";
const PARAMETER: &str = "/rpc/aimrt.protocols.parameter_plugin.ParameterService";
const WAIT: Duration = Duration::from_secs(30);

/// Starts `config/<name>.yaml` on port 0, with `extra` appended (a module's own node).
fn start(name: &str, extra: &str) -> (Running, String) {
    let cfg = format!("{}{extra}", with_port(&repo_config(name), 0));
    let mut running = Running::start(&cfg);
    let addr = running.http_address(WAIT);
    (running, addr)
}

/// POSTs `body` as JSON to `<service>/<method>`: the HTTP status and the answer as JSON.
fn call(addr: &str, service: &str, method: &str, body: Value) -> Value {
    let (status, text) = http(
        addr,
        "POST",
        &format!("{service}/{method}"),
        &[("content-type", "application/json")],
        body.to_string().as_bytes(),
    );
    assert_eq!(status, 200, "{method}: {text}");
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{method}: {e}: {text}"))
}

/// The answer's code (AimRT's JSON writes every field, 0 and "" too; a uint64, as
/// `SetParameterRsp.code`, as a string).
fn code(answer: &Value) -> u64 {
    match &answer["code"] {
        Value::String(s) => s.parse().ok(),
        n => n.as_u64(),
    }
    .unwrap_or_else(|| panic!("no code: {answer}"))
}

fn msg(answer: &Value) -> &str {
    answer["msg"]
        .as_str()
        .unwrap_or_else(|| panic!("no msg: {answer}"))
}

#[test]
fn log_levels_are_read_and_set_while_the_process_runs_in_every_library() {
    let (mut running, addr) = start("log_control_plugin", "LoggerModule:\n  interval_ms: 50\n");
    running.wait_for("Test info log", WAIT);

    // Every logger: the runtime's, the plugins' and the module's, with AimRT's names.
    let all = call(
        &addr,
        LOG_CONTROL,
        "GetModuleLogLevel",
        json!({"module_names": []}),
    );
    assert_eq!(code(&all), 0, "{all}");
    let map = &all["module_log_level_map"];
    assert_eq!(map["LoggerModule"], "Info", "{all}");
    assert_eq!(map["core"], "Info", "{all}");
    assert_eq!(map["log_control_plugin"], "Info", "{all}");
    assert!(
        !running.text().contains("Test trace log"),
        "{}",
        running.text()
    );
    // As it comes over the wire: the names in byte order.
    let (_, raw) = http(
        &addr,
        "POST",
        &format!("{LOG_CONTROL}/GetModuleLogLevel"),
        &[("content-type", "application/json")],
        b"{}",
    );
    assert_eq!(
        raw,
        r#"{"code":0,"msg":"","module_log_level_map":{"LoggerModule":"Info","core":"Info","log_control_plugin":"Info","logger_pkg":"Info","net_plugin":"Info"}}"#
    );

    // Raised: the module's library writes its Trace lines from now on (it had filtered
    // them out at Info before reading a level).
    let set = call(
        &addr,
        LOG_CONTROL,
        "SetModuleLogLevel",
        json!({"module_log_level_map": {"LoggerModule": "Trace"}}),
    );
    assert_eq!(code(&set), 0, "{set}");
    running.wait_for("Log level of 'LoggerModule': Info -> Trace", WAIT);
    running.wait_for("Test trace log", WAIT);
    running.wait_for("Test debug log", WAIT);

    // Lowered, any case: only Error and Fatal lines of the module are written after it.
    let set = call(
        &addr,
        LOG_CONTROL,
        "SetModuleLogLevel",
        json!({"module_log_level_map": {"LoggerModule": "ERROR"}}),
    );
    assert_eq!(code(&set), 0, "{set}");
    running.wait_for("Log level of 'LoggerModule': Trace -> Error", WAIT);
    let lines = running.collect_for(Duration::from_millis(600), "[LoggerModule]");
    assert!(lines.len() >= 2, "{}", running.text());
    for (_, line) in &lines {
        assert!(
            line.contains("[Error]") || line.contains("[Fatal]"),
            "a line below Error after the level was set: {line}"
        );
    }

    // Refused, all or nothing: an unknown logger (named, with the loggers there are) and
    // an unknown level (aimrt-rs: code 2). The level stays Error.
    let refused = call(
        &addr,
        LOG_CONTROL,
        "SetModuleLogLevel",
        json!({"module_log_level_map": {"LoggerModule": "Info", "LogerModule": "Info"}}),
    );
    assert_eq!(code(&refused), 1, "{refused}");
    assert!(
        msg(&refused).starts_with(
            "INVALID_MODULE_NAME: no logger 'LogerModule'; did you mean 'LoggerModule'?"
        ),
        "{refused}"
    );
    let refused = call(
        &addr,
        LOG_CONTROL,
        "SetModuleLogLevel",
        json!({"module_log_level_map": {"LoggerModule": "Loud"}}),
    );
    assert_eq!(code(&refused), 2, "{refused}");
    assert!(
        msg(&refused).starts_with("INVALID_LOG_LEVEL: logger 'LoggerModule'"),
        "{refused}"
    );
    let some = call(
        &addr,
        LOG_CONTROL,
        "GetModuleLogLevel",
        json!({"module_names": ["LoggerModule", "Nobody"]}),
    );
    assert_eq!(code(&some), 1, "{some}");
    assert!(msg(&some).contains("no logger 'Nobody'"), "{some}");
    assert_eq!(
        some["module_log_level_map"],
        json!({"LoggerModule": "Error"}),
        "{some}"
    );
    // In `pb`, as AimRT's C++ clients call it: `module_names: ["LoggerModule"]` in, the map
    // (field 3, one entry) out, code and msg at their defaults.
    let (status, body) = http(
        &addr,
        "POST",
        &format!("{LOG_CONTROL}/GetModuleLogLevel"),
        &[("content-type", "application/protobuf")],
        b"\x0a\x0cLoggerModule",
    );
    assert_eq!(status, 200, "{body}");
    assert_eq!(
        body.as_bytes(),
        b"\x1a\x15\x0a\x0cLoggerModule\x12\x05Error"
    );

    // A body that is not the request is a bad request, answered and not applied.
    let (status, text) = http(
        &addr,
        "POST",
        &format!("{LOG_CONTROL}/SetModuleLogLevel"),
        &[("content-type", "application/json")],
        br#"{"module_log_level_map": ["Trace"]}"#,
    );
    assert_eq!(status, 400, "{text}");
    assert_eq!(running.interrupt(WAIT), Some(0), "{}", running.text());
}

#[test]
fn module_parameters_are_set_read_listed_dumped_and_loaded_over_http() {
    let (mut running, addr) = start("parameter_plugin", "");
    running.wait_for("Set parameter, key: 'key-1'", WAIT);
    let p = |method: &str, body: Value| call(&addr, PARAMETER, method, body);
    let module = "ParameterModule";

    let set = p(
        "Set",
        json!({"module_name": module, "parameter_key": "speed", "parameter_value": "0.5"}),
    );
    assert_eq!(code(&set), 0, "{set}");
    let got = p(
        "Get",
        json!({"module_name": module, "parameter_key": "speed"}),
    );
    assert_eq!(got["parameter_value"], "0.5", "{got}");
    // The module's own values are there too.
    let keys = p("List", json!({"module_name": module}));
    let keys: Vec<&str> = keys["parameter_keys"]
        .as_array()
        .unwrap_or_else(|| panic!("{keys}"))
        .iter()
        .filter_map(Value::as_str)
        .collect();
    assert!(
        keys.contains(&"speed") && keys.contains(&"key-1"),
        "{keys:?}"
    );

    // Load: many at once; an empty value removes a key.
    let loaded = p(
        "Load",
        json!({"module_parameter_map": {module: {"value": {"mode": "slow", "speed": ""}}}}),
    );
    assert_eq!(code(&loaded), 0, "{loaded}");
    let dump = p("Dump", json!({}));
    let values = &dump["module_parameter_map"][module]["value"];
    assert_eq!(values["mode"], "slow", "{dump}");
    assert!(values.get("speed").is_none(), "{dump}");
    // A key that is not set reads as empty, as AimRT.
    let gone = p(
        "Get",
        json!({"module_name": module, "parameter_key": "speed"}),
    );
    assert_eq!(code(&gone), 0, "{gone}");
    assert_eq!(gone["parameter_value"], "", "{gone}");

    // An unknown module is refused, named with the modules there are, and a Load that
    // names one changes nothing.
    let refused = p(
        "Load",
        json!({"module_parameter_map": {
            module: {"value": {"mode": "fast"}},
            "ParameterModul": {"value": {"x": "1"}},
        }}),
    );
    assert_eq!(code(&refused), 1, "{refused}");
    assert_eq!(
        msg(&refused),
        "INVALID_MODULE_NAME: no module 'ParameterModul'; did you mean 'ParameterModule'? (the modules: ParameterModule)"
    );
    let mode = p(
        "Get",
        json!({"module_name": module, "parameter_key": "mode"}),
    );
    assert_eq!(mode["parameter_value"], "slow", "{mode}");
    for (method, body) in [
        (
            "Set",
            json!({"module_name": "x", "parameter_key": "k", "parameter_value": "v"}),
        ),
        ("Get", json!({"module_name": "x", "parameter_key": "k"})),
        ("List", json!({"module_name": "x"})),
        ("Dump", json!({"module_names": [module, "x"]})),
    ] {
        let answer = p(method, body);
        assert_eq!(code(&answer), 1, "{method}: {answer}");
        assert!(msg(&answer).contains("no module 'x'"), "{method}: {answer}");
    }
    assert_eq!(running.interrupt(WAIT), Some(0), "{}", running.text());
}
