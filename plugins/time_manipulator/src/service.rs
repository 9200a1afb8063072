//! `TimeManipulatorService`: requests and responses in protobuf's JSON mapping.
//!
//! Requests accept the proto field names (`executor_name`, `time_ratio`) and their JSON
//! names (`executorName`, `timeRatio`); a double may be a number, a numeric string, or
//! `"NaN"`/`"Infinity"`/`"-Infinity"` as in protobuf JSON. A missing field, an unknown
//! field or a value of the wrong type is a bad request (HTTP 400). Responses print the
//! ratio minimally (`2`, not `2.0`), as AimRT's JSON does.

use aimrt_plugin_api::channel::json_double;
use aimrt_plugin_api::ServiceError;
use serde_json::Value;

use crate::Registry;

/// The service's methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Method {
    SetTimeRatio,
    Pause,
    GetTimeRatio,
}

impl Method {
    pub(crate) const ALL: [Method; 3] = [Method::SetTimeRatio, Method::Pause, Method::GetTimeRatio];

    pub(crate) fn name(self) -> &'static str {
        match self {
            Method::SetTimeRatio => "SetTimeRatio",
            Method::Pause => "Pause",
            Method::GetTimeRatio => "GetTimeRatio",
        }
    }

    /// The request's fields: (proto name, JSON name).
    fn fields(self) -> &'static [(&'static str, &'static str)] {
        match self {
            Method::SetTimeRatio => &[
                ("executor_name", "executorName"),
                ("time_ratio", "timeRatio"),
            ],
            Method::Pause | Method::GetTimeRatio => &[("executor_name", "executorName")],
        }
    }
}

/// AimRT's `CommonRsp`.
#[derive(Debug, PartialEq)]
pub(crate) struct CommonRsp {
    pub(crate) time_ratio: f64,
    pub(crate) code: u32,
    pub(crate) msg: String,
}

const INVALID_EXECUTOR_NAME: u32 = 1;
const INVALID_TIME_RATIO: u32 = 2;

impl CommonRsp {
    fn ok(time_ratio: f64) -> CommonRsp {
        CommonRsp {
            time_ratio,
            code: 0,
            msg: String::new(),
        }
    }

    pub(crate) fn to_json(&self) -> Vec<u8> {
        // AimRT's field order, and its protobuf's double (`2`, not `2.0`).
        format!(
            r#"{{"time_ratio":{},"code":{},"msg":{}}}"#,
            json_double(self.time_ratio),
            self.code,
            Value::from(self.msg.as_str())
        )
        .into_bytes()
    }
}

fn bad(message: impl Into<String>) -> ServiceError {
    ServiceError::BadRequest(message.into())
}

/// A request body: a JSON object whose keys are unique, or any other JSON value.
enum Body {
    Object(serde_json::Map<String, Value>),
    Other,
}

impl<'de> serde::Deserialize<'de> for Body {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visit;
        impl<'de> serde::de::Visitor<'de> for Visit {
            type Value = Body;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a JSON object")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<Body, A::Error> {
                let mut obj = serde_json::Map::new();
                while let Some(key) = map.next_key::<String>()? {
                    if obj.contains_key(&key) {
                        return Err(serde::de::Error::custom(format_args!(
                            "field '{key}' is given twice; give each field once"
                        )));
                    }
                    let value = map.next_value::<Value>()?;
                    obj.insert(key, value);
                }
                Ok(Body::Object(obj))
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Body, A::Error> {
                while seq.next_element::<serde::de::IgnoredAny>()?.is_some() {}
                Ok(Body::Other)
            }
            fn visit_bool<E>(self, _: bool) -> Result<Body, E> {
                Ok(Body::Other)
            }
            fn visit_i64<E>(self, _: i64) -> Result<Body, E> {
                Ok(Body::Other)
            }
            fn visit_u64<E>(self, _: u64) -> Result<Body, E> {
                Ok(Body::Other)
            }
            fn visit_f64<E>(self, _: f64) -> Result<Body, E> {
                Ok(Body::Other)
            }
            fn visit_str<E>(self, _: &str) -> Result<Body, E> {
                Ok(Body::Other)
            }
            fn visit_unit<E>(self) -> Result<Body, E> {
                Ok(Body::Other)
            }
        }
        d.deserialize_any(Visit)
    }
}

/// Reads the request of `method` from JSON: `(executor_name, time_ratio)`.
pub(crate) fn parse(method: Method, request: &[u8]) -> Result<(String, f64), ServiceError> {
    let value: Body = serde_json::from_slice(request).map_err(|e| {
        if e.is_data() {
            bad(format!("{e}"))
        } else {
            bad(format!("the body is not valid JSON: {e}"))
        }
    })?;
    let Body::Object(obj) = value else {
        return Err(bad(format!(
            "the body must be a JSON object such as {}",
            example(method)
        )));
    };
    let fields = method.fields();
    for key in obj.keys() {
        if !fields.iter().any(|(p, j)| key == p || key == j) {
            let known: Vec<&str> = fields.iter().map(|f| f.0).collect();
            return Err(bad(format!(
                "unknown field '{key}' for {}; its fields are {}",
                method.name(),
                known.join(", ")
            )));
        }
    }
    let field = |(proto, json): (&str, &str)| -> Result<&Value, ServiceError> {
        if obj.contains_key(proto) && obj.contains_key(json) {
            return Err(bad(format!(
                "field '{proto}' is given twice (also as '{json}')"
            )));
        }
        match obj.get(proto).or_else(|| obj.get(json)) {
            Some(Value::Null) | None => Err(bad(format!(
                "missing field '{proto}'; send {}",
                example(method)
            ))),
            Some(v) => Ok(v),
        }
    };
    let name = match field(fields[0])? {
        Value::String(s) => s.clone(),
        other => {
            return Err(bad(format!(
                "field 'executor_name' must be a string, got {other}"
            )))
        }
    };
    let ratio = if method == Method::SetTimeRatio {
        double(field(fields[1])?)?
    } else {
        0.0
    };
    Ok((name, ratio))
}

/// A protobuf JSON double: a number, a numeric string, or NaN / ±Infinity as strings.
fn double(v: &Value) -> Result<f64, ServiceError> {
    match v {
        Value::Number(n) => n
            .as_f64()
            .ok_or_else(|| bad(format!("field 'time_ratio': {n} is not a double"))),
        Value::String(s) => match s.as_str() {
            "NaN" => Ok(f64::NAN),
            "Infinity" => Ok(f64::INFINITY),
            "-Infinity" => Ok(f64::NEG_INFINITY),
            other => other.trim().parse::<f64>().map_err(|_| {
                bad(format!(
                    "field 'time_ratio' must be a number, got the string '{other}'"
                ))
            }),
        },
        other => Err(bad(format!(
            "field 'time_ratio' must be a number, got {other}"
        ))),
    }
}

fn example(method: Method) -> &'static str {
    match method {
        Method::SetTimeRatio => r#"{"executor_name": "time_schedule_executor", "time_ratio": 2.0}"#,
        Method::Pause | Method::GetTimeRatio => r#"{"executor_name": "time_schedule_executor"}"#,
    }
}

/// Runs one call.
pub(crate) fn call(method: Method, registry: &Registry, name: &str, ratio: f64) -> CommonRsp {
    let found = {
        let executors = registry.read().unwrap_or_else(|e| e.into_inner());
        executors.get(name).cloned().ok_or_else(|| {
            let names: Vec<&str> = executors.keys().map(String::as_str).collect();
            format!(
                "INVALID_EXECUTOR_NAME: no time_manipulator executor is named '{name}'{}; the time_manipulator executors: {}",
                aimrt_plugin_api::__private::did_you_mean(name, names.iter().copied()),
                if names.is_empty() { "none".to_owned() } else { names.join(", ") }
            )
        })
    };
    let exec = match found {
        Ok(exec) => exec,
        Err(msg) => {
            return CommonRsp {
                time_ratio: 0.0,
                code: INVALID_EXECUTOR_NAME,
                msg,
            }
        }
    };
    match method {
        Method::SetTimeRatio => match exec.set_time_ratio(ratio) {
            Ok(now) => CommonRsp::ok(now),
            Err(e) => CommonRsp {
                time_ratio: exec.time_ratio(),
                code: INVALID_TIME_RATIO,
                msg: format!("INVALID_TIME_RATIO: {e}; the ratio stays"),
            },
        },
        Method::Pause => {
            exec.pause();
            CommonRsp::ok(0.0)
        }
        Method::GetTimeRatio => CommonRsp::ok(exec.time_ratio()),
    }
}

/// The service function: JSON in, JSON out.
pub(crate) fn handle(
    method: Method,
    registry: &Registry,
    format: &str,
    request: &[u8],
) -> Result<Vec<u8>, ServiceError> {
    if format != "json" {
        return Err(ServiceError::UnsupportedFormat(format!(
            "TimeManipulatorService speaks json, not '{format}'"
        )));
    }
    let (name, ratio) = parse(method, request)?;
    Ok(call(method, registry, &name, ratio).to_json())
}

#[cfg(test)]
mod tests {
    use super::*;
    use aimrt_plugin_api::{Executor, ExecutorArgs, ExecutorRef, ThreadFactory};

    fn registry(name: &str, init_ratio: f64) -> (Registry, ExecutorRef) {
        let pool = aimrt_std_executors::create_executor(
            "simple_thread",
            ExecutorArgs {
                name: "pool",
                options_json: "null",
                location: "test",
                bound: Vec::new(),
                threads: ThreadFactory::plain(),
            },
        )
        .unwrap();
        let sim = aimrt_std_executors::create_time_manipulator(ExecutorArgs {
            name,
            options_json: &format!(r#"{{"bind_executor": "pool", "init_ratio": {init_ratio}}}"#),
            location: "test",
            bound: vec![Some(pool)],
            threads: ThreadFactory::plain(),
        })
        .unwrap();
        let reg = Registry::default();
        reg.write().unwrap().insert(name.to_owned(), sim);
        (reg, pool)
    }

    fn json(method: Method, reg: &Registry, body: &str) -> Result<Value, ServiceError> {
        handle(method, reg, "json", body.as_bytes()).map(|b| serde_json::from_slice(&b).unwrap())
    }

    #[test]
    fn ratios_are_exact_and_every_edge_case_is_answered() {
        let (reg, pool) = registry("sim", 2.0);
        let set = |r: &str| {
            json(
                Method::SetTimeRatio,
                &reg,
                &format!(r#"{{"executor_name": "sim", "time_ratio": {r}}}"#),
            )
            .unwrap()
        };
        assert_eq!(
            set("2.5"),
            serde_json::json!({"time_ratio": 2.5, "code": 0, "msg": ""})
        );
        assert_eq!(
            set("2.0"),
            serde_json::json!({"time_ratio": 2, "code": 0, "msg": ""})
        );
        assert_eq!(set("0.3")["time_ratio"], 0.3);
        assert_eq!(set("0.7")["time_ratio"], 0.7);
        assert_eq!(set("1000000")["time_ratio"], 1_000_000);
        // ≤ 0 pauses (negative as 0).
        assert_eq!(set("0")["time_ratio"], 0);
        assert_eq!(set("-1")["time_ratio"], 0);
        assert_eq!(set("1e-300")["time_ratio"], 1e-300);
        // The text is AimRT's protobuf's (`%.15g`): `1e-05`, where serde_json writes `1e-5`.
        let raw = handle(
            Method::SetTimeRatio,
            &reg,
            "json",
            br#"{"executor_name": "sim", "time_ratio": 0.00001}"#,
        )
        .unwrap();
        assert_eq!(raw, br#"{"time_ratio":1e-05,"code":0,"msg":""}"#);
        // Refused: code 2, the ratio stays.
        set("1.5");
        for refused in [
            r#""NaN""#,
            r#""Infinity""#,
            r#""-Infinity""#,
            "1000000.5",
            "1e300",
        ] {
            let r = set(refused);
            assert_eq!(r["code"], 2, "{refused}");
            assert_eq!(r["time_ratio"], 1.5, "{refused}");
            assert!(
                r["msg"].as_str().unwrap().starts_with("INVALID_TIME_RATIO"),
                "{r}"
            );
        }
        // Numeric strings and the JSON field names are protobuf JSON too.
        assert_eq!(set(r#""3.25""#)["time_ratio"], 3.25);
        assert_eq!(
            json(
                Method::SetTimeRatio,
                &reg,
                r#"{"executorName": "sim", "timeRatio": 4}"#
            )
            .unwrap()["time_ratio"],
            4
        );
        // Pause and get.
        assert_eq!(
            json(Method::Pause, &reg, r#"{"executor_name": "sim"}"#).unwrap(),
            serde_json::json!({"time_ratio": 0, "code": 0, "msg": ""})
        );
        assert_eq!(
            json(Method::GetTimeRatio, &reg, r#"{"executor_name": "sim"}"#).unwrap()["time_ratio"],
            0
        );
        // Unknown executor: code 1, as AimRT.
        for m in Method::ALL {
            let body = if m == Method::SetTimeRatio {
                r#"{"executor_name": "nope", "time_ratio": 1}"#
            } else {
                r#"{"executor_name": "nope"}"#
            };
            assert_eq!(
                json(m, &reg, body).unwrap(),
                serde_json::json!({"time_ratio": 0, "code": 1, "msg": "INVALID_EXECUTOR_NAME: no time_manipulator executor is named 'nope'; the time_manipulator executors: sim"})
            );
        }
        pool.raw().shutdown();
        reg.read().unwrap()["sim"].shutdown();
    }

    #[test]
    fn malformed_requests_are_bad_requests() {
        let (reg, pool) = registry("sim", 1.0);
        for (method, body, says) in [
            (Method::SetTimeRatio, "", "not valid JSON"),
            (Method::SetTimeRatio, "{", "not valid JSON"),
            (Method::SetTimeRatio, "[1]", "must be a JSON object"),
            (
                Method::SetTimeRatio,
                r#"{"executor_name": "sim"}"#,
                "missing field 'time_ratio'",
            ),
            (
                Method::SetTimeRatio,
                r#"{"time_ratio": 1}"#,
                "missing field 'executor_name'",
            ),
            (
                Method::SetTimeRatio,
                r#"{"executor_name": null, "time_ratio": 1}"#,
                "missing field 'executor_name'",
            ),
            (
                Method::SetTimeRatio,
                r#"{"executor_name": 3, "time_ratio": 1}"#,
                "must be a string",
            ),
            (
                Method::SetTimeRatio,
                r#"{"executor_name": "sim", "time_ratio": "fast"}"#,
                "must be a number",
            ),
            (
                Method::SetTimeRatio,
                r#"{"executor_name": "sim", "time_ratio": true}"#,
                "must be a number",
            ),
            (
                Method::SetTimeRatio,
                r#"{"executor_name": "sim", "time_ratio": 1, "x": 1}"#,
                "unknown field 'x'",
            ),
            (
                Method::SetTimeRatio,
                r#"{"executor_name": "sim", "executorName": "sim", "time_ratio": 1}"#,
                "given twice",
            ),
            (
                Method::SetTimeRatio,
                r#"{"executor_name": "nope", "executor_name": "sim", "time_ratio": 1}"#,
                "field 'executor_name' is given twice",
            ),
            (
                Method::Pause,
                r#"{"executor_name": "sim", "time_ratio": 1}"#,
                "unknown field 'time_ratio'",
            ),
            (Method::GetTimeRatio, "{}", "missing field 'executor_name'"),
        ] {
            match handle(method, &reg, "json", body.as_bytes()) {
                Err(ServiceError::BadRequest(m)) => assert!(m.contains(says), "{body}: {m}"),
                other => panic!("{body}: {other:?}"),
            }
        }
        assert!(matches!(
            handle(Method::Pause, &reg, "pb", b""),
            Err(ServiceError::UnsupportedFormat(_))
        ));
        // Nothing above changed the ratio.
        assert_eq!(reg.read().unwrap()["sim"].time_ratio(), 1.0);
        pool.raw().shutdown();
        reg.read().unwrap()["sim"].shutdown();
    }

    #[test]
    fn random_bodies_never_panic() {
        let (reg, pool) = registry("sim", 1.0);
        let pieces: [&[u8]; 14] = [
            b"{",
            b"}",
            b"\"executor_name\"",
            b":",
            b"\"sim\"",
            b",",
            b"\"time_ratio\"",
            b"1e999",
            b"-0",
            b"null",
            b"[",
            b"\xff\xfe",
            b"\"NaN\"",
            b"0.5",
        ];
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        for _ in 0..20_000 {
            let mut body = Vec::new();
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            let mut s = seed;
            for _ in 0..(s % 12) {
                body.extend_from_slice(pieces[(s % 14) as usize]);
                s /= 14;
            }
            for m in Method::ALL {
                let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    handle(m, &reg, "json", &body)
                }));
                assert!(r.is_ok(), "{:?}", String::from_utf8_lossy(&body));
            }
        }
        let ratio = reg.read().unwrap()["sim"].time_ratio();
        assert!(ratio.is_finite() && (0.0..=1e6).contains(&ratio));
        pool.raw().shutdown();
        reg.read().unwrap()["sim"].shutdown();
    }
}
