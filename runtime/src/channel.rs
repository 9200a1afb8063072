//! `aimrt.channel`: read and checked now, so an AimRT channel config is accepted or refused
//! with a clear error; publish/subscribe itself is not implemented yet (issue 8).

use std::collections::HashMap;

use aimrt_plugin_api::ffi::RawExecutor;
use serde::Deserialize;

use crate::config::Config;
use crate::routing::{listed_backends, Rules};
use crate::Error;
use aimrt_plugin_api::__private::{did_you_mean, read_options};

/// Options of the built-in `local` backend, as AimRT.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LocalOptions {
    #[serde(default = "yes")]
    subscriber_use_inline_executor: bool,
    #[serde(default)]
    subscriber_executor: String,
}

fn yes() -> bool {
    true
}

/// The checked channel config.
#[derive(Default)]
pub(crate) struct ChannelConfig {
    /// Backends of publish topics.
    pub(crate) pub_rules: Rules,
    /// Backends of subscribe topics.
    pub(crate) sub_rules: Rules,
    /// `local`'s subscriber executor (`None`: inline on the publisher's thread).
    pub(crate) local_executor: Option<String>,
}

/// Checks `aimrt.channel` against the built executors.
pub(crate) fn configure(
    config: &Config,
    executors: &HashMap<String, RawExecutor>,
) -> Result<ChannelConfig, Error> {
    let Some(section) = config.aimrt.channel.as_ref() else {
        return Ok(ChannelConfig::default());
    };
    let mut out = ChannelConfig::default();
    let listed = listed_backends(config, &section.backends, "aimrt.channel")?;
    for entry in &section.backends {
        let ty = entry.type_name.value.as_str();
        if ty != "local" {
            return Err(config.error(
                &entry.type_name,
                format!(
                    "unknown channel backend type '{ty}'{}; known: local (plugins add more)",
                    did_you_mean(ty, ["local"])
                ),
            ));
        }
        let (json, location) = config.options_of(entry.options.as_ref(), &entry.type_name);
        let o: LocalOptions = read_options(&json, || {
            format!("options of channel backend 'local' at {location}")
        })
        .map_err(|e| config.error(&entry.type_name, e.to_string()))?;
        if o.subscriber_use_inline_executor {
            continue;
        }
        let name = o.subscriber_executor;
        if name.is_empty() {
            return Err(config.error(&entry.type_name, "subscriber_use_inline_executor is false, so subscriber_executor must name the executor that runs the subscribers"));
        }
        if !executors.contains_key(&name) {
            return Err(config.error(
                &entry.type_name,
                format!(
                    "subscriber_executor '{name}' is not an executor{}",
                    did_you_mean(&name, executors.keys().map(String::as_str))
                ),
            ));
        }
        out.local_executor = Some(name);
    }
    out.pub_rules = Rules::compile(
        config,
        &section.pub_topics_options,
        &listed,
        "aimrt.channel",
    )?;
    out.sub_rules = Rules::compile(
        config,
        &section.sub_topics_options,
        &listed,
        "aimrt.channel",
    )?;
    Ok(out)
}
