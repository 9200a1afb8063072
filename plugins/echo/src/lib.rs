//! `echo_plugin`: prints every message of the configured topics to the log, as AimRT's
//! echo_plugin does, by type name: the message types come from type support packages
//! (`type_support_pkgs`), so the plugin needs no Rust type of its own.
//!
//! ```yaml
//! aimrt:
//!   plugin:
//!     plugins:
//!       - name: echo_plugin
//!         path: ./target/debug/libaimrt_echo_plugin.so
//!         options:
//!           type_support_pkgs:
//!             - path: ./target/debug/libexample_pb_ts.so
//!           topic_meta_list:
//!             - topic_name: test_topic
//!               msg_type: pb:aimrt.protocols.example.ExampleEventMsg
//!               echo_type: json     # json (default), yaml, or any format of the type
//! ```
//!
//! Each message is one INFO line `\n---\n<text>\n---\n`: `json` indented as AimRT's
//! (3 spaces), `yaml` as a YAML document, any other format of the type (e.g. `pb`) as hex.
//! The topics must be routed to a backend by `aimrt.channel.sub_topics_options`.
#![deny(unsafe_code)]

use std::collections::HashSet;

use aimrt_plugin_api::ffi::{formats_of, RawMessage, TypeSupportVtable};
use aimrt_plugin_api::{Error, Plugin, PluginOptions, Registrar, TypeSupportPkg};
use serde::Deserialize;

#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct TopicMeta {
    topic_name: String,
    msg_type: String,
    #[serde(default = "json")]
    echo_type: String,
}

fn json() -> String {
    "json".into()
}

#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
struct Options {
    #[serde(default)]
    type_support_pkgs: Vec<TypeSupportPkg>,
    #[serde(default)]
    topic_meta_list: Vec<TopicMeta>,
}

struct EchoPlugin;

/// The plugin, as `libaimrt_echo_plugin.so` exports it (`plugins/echo/so`).
pub fn plugin() -> Box<dyn Plugin> {
    Box::new(EchoPlugin)
}

impl Plugin for EchoPlugin {
    fn name(&self) -> &str {
        "echo_plugin"
    }

    fn initialize(
        &mut self,
        registrar: &mut Registrar<'_>,
        options: &PluginOptions,
    ) -> Result<(), Error> {
        let o: Options = registrar.read_options(options)?;
        let bad = |message: String| options.invalid(message);
        let types = registrar
            .load_type_support_pkgs(&o.type_support_pkgs)
            .map_err(bad)?;
        let channel = registrar.core()?.channel()?;
        let mut seen = HashSet::new();
        for (i, t) in o.topic_meta_list.iter().enumerate() {
            let ts = types
                .get(&t.msg_type)
                .map_err(|e| bad(format!("topic_meta_list[{i}].{e}")))?;
            let formats = formats_of(ts);
            if t.echo_type != "yaml" && !formats.contains(&t.echo_type) {
                return Err(bad(format!(
                    "topic_meta_list[{i}].echo_type '{}' is not a format of '{}'; use yaml or one of: {}",
                    t.echo_type,
                    t.msg_type,
                    formats.join(", ")
                )));
            }
            if t.echo_type == "yaml" && !formats.iter().any(|f| f == "json") {
                return Err(bad(format!(
                    "topic_meta_list[{i}].echo_type yaml needs the json format, which '{}' lacks",
                    t.msg_type
                )));
            }
            if !seen.insert((t.topic_name.clone(), t.msg_type.clone())) {
                return Err(bad(format!(
                    "topic_meta_list[{i}]: topic '{}' with type '{}' is listed twice",
                    t.topic_name, t.msg_type
                )));
            }
            subscribe(&channel, &t.topic_name, ts, t.echo_type.clone())?;
        }
        Ok(())
    }
}

fn subscribe(
    channel: &aimrt_plugin_api::channel::ChannelRef,
    topic: &str,
    ts: &'static TypeSupportVtable,
    echo_type: String,
) -> Result<(), Error> {
    channel.subscribe_raw(topic, ts, move |_, msg| {
        let text = render(&msg, &echo_type)?;
        tracing::info!("\n---\n{text}\n---\n");
        Ok(())
    })
}

/// `msg` as the text echo prints for `echo_type`; `Err` says why it cannot be shown.
fn render(msg: &RawMessage, echo_type: &str) -> Result<String, String> {
    let format = if echo_type == "yaml" {
        "json"
    } else {
        echo_type
    };
    let bytes = msg
        .encode(format)
        .map_err(|e| format!("Can not serialize msg type with echo type '{echo_type}': {e}"))?;
    match echo_type {
        "json" => Ok(pretty_json(&bytes)),
        "yaml" => {
            let value: serde_json::Value = serde_json::from_slice(&bytes)
                .map_err(|e| format!("the message's json is not valid: {e}"))?;
            serde_saphyr::to_string(&value)
                .map(|t| t.trim_end().to_owned())
                .map_err(|e| format!("cannot write the message as yaml: {e}"))
        }
        _ => Ok(bytes.iter().map(|b| format!("{b:02x}")).collect()),
    }
}

/// JSON indented by 3 spaces (AimRT prints with jsoncpp's styled writer); text that is
/// not JSON is kept as it is, with a warning.
fn pretty_json(bytes: &[u8]) -> String {
    use serde::Serialize;
    let Ok(value) = serde_json::from_slice::<serde_json::Value>(bytes) else {
        tracing::warn!("Invalid json string, will keep original string.");
        return String::from_utf8_lossy(bytes).into_owned();
    };
    let mut out = Vec::new();
    let mut ser = serde_json::Serializer::with_formatter(
        &mut out,
        serde_json::ser::PrettyFormatter::with_indent(b"   "),
    );
    match value.serialize(&mut ser) {
        Ok(()) => String::from_utf8_lossy(&out).into_owned(),
        Err(_) => String::from_utf8_lossy(bytes).into_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_is_indented_as_aimrt_prints_it() {
        assert_eq!(
            pretty_json(br#"{"msg":"count: 1","num":1}"#),
            "{\n   \"msg\": \"count: 1\",\n   \"num\": 1\n}"
        );
        assert_eq!(pretty_json(b"not json"), "not json");
    }
}
