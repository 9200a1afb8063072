//! The plugin's options, AimRT's keys, checked strictly.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// `record_actions[i]`.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Action<O> {
    pub(crate) name: String,
    pub(crate) options: O,
}

/// The plugin's options.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Options {
    /// Renames the control service (default
    /// `aimrt.protocols.record_playback_plugin.RecordPlaybackService`).
    #[serde(default)]
    pub(crate) service_name: String,
    #[serde(default)]
    pub(crate) type_support_pkgs: Vec<aimrt_plugin_api::TypeSupportPkg>,
    /// Runs the timed chunk flushes (`msg_write_interval_time`).
    #[serde(default)]
    pub(crate) timer_executor: String,
    #[serde(default)]
    pub(crate) record_actions: Vec<Action<RecordOptions>>,
    #[serde(default)]
    pub(crate) playback_actions: Vec<Action<PlaybackOptions>>,
}

/// `record_actions[i].options`.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RecordOptions {
    pub(crate) bag_path: String,
    pub(crate) mode: String,
    pub(crate) executor: String,
    #[serde(default)]
    pub(crate) max_preparation_duration_s: u64,
    #[serde(default = "yes")]
    pub(crate) record_enabled: bool,
    #[serde(default)]
    pub(crate) storage_policy: StoragePolicy,
    #[serde(default, deserialize_with = "attributes")]
    pub(crate) extra_attributes: BTreeMap<String, serde_json::Value>,
    #[serde(default)]
    pub(crate) extra_file_path: Vec<String>,
    #[serde(default)]
    pub(crate) topic_meta_list: Vec<TopicMeta>,
}

fn yes() -> bool {
    true
}

/// `extra_attributes`: a map, or null (none).
fn attributes<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<BTreeMap<String, serde_json::Value>, D::Error> {
    Ok(Option::<BTreeMap<String, serde_json::Value>>::deserialize(d)?.unwrap_or_default())
}

/// `storage_policy`.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub(crate) struct StoragePolicy {
    pub(crate) max_bag_size_m: u64,
    pub(crate) max_bag_num: u64,
    pub(crate) msg_write_interval: u64,
    pub(crate) msg_write_interval_time: u64,
    compression_mode: String,
    compression_level: String,
    pub(crate) new_folder_daily: bool,
    #[serde(skip)]
    pub(crate) compression: Compression,
    #[serde(skip)]
    pub(crate) level: u32,
}

impl Default for StoragePolicy {
    fn default() -> Self {
        StoragePolicy {
            max_bag_size_m: 2048,
            max_bag_num: 0,
            msg_write_interval: 1000,
            msg_write_interval_time: 1000,
            compression_mode: "zstd".into(),
            compression_level: "default".into(),
            new_folder_daily: false,
            compression: Compression::Zstd,
            level: 0,
        }
    }
}

/// Chunk compression.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) enum Compression {
    None,
    Lz4,
    #[default]
    Zstd,
}

impl StoragePolicy {
    /// Reads the compression mode and level (case-insensitive; AimRT's level is
    /// case-sensitive); `Err` says what would be right.
    pub(crate) fn resolve(&mut self) -> Result<(), String> {
        self.compression = match self.compression_mode.to_ascii_lowercase().as_str() {
            "none" => Compression::None,
            "lz4" => Compression::Lz4,
            "zstd" => Compression::Zstd,
            other => {
                return Err(format!(
                    "storage_policy.compression_mode '{other}' is not none, lz4 or zstd"
                ))
            }
        };
        // zstd's levels; lz4 takes the same numbers up to 12; 0 is the library default.
        let level = match self.compression_level.to_ascii_lowercase().as_str() {
            "fastest" => 1,
            "fast" => 3,
            "default" => 0,
            "slow" => 9,
            "slowest" => 19,
            other => {
                return Err(format!(
                    "storage_policy.compression_level '{other}' is not fastest, fast, default, slow or slowest"
                ))
            }
        };
        self.level = if self.compression == Compression::Lz4 {
            level.min(12)
        } else {
            level
        };
        if self.max_bag_size_m == 0 {
            return Err("storage_policy.max_bag_size_m must be at least 1 (MiB)".into());
        }
        if self.msg_write_interval_time == 0 {
            return Err("storage_policy.msg_write_interval_time must be at least 1 (ms)".into());
        }
        Ok(())
    }
}

/// `topic_meta_list[j]`.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct TopicMeta {
    pub(crate) topic_name: String,
    pub(crate) msg_type: String,
    #[serde(default)]
    pub(crate) serialization_type: Option<String>,
    #[serde(default)]
    pub(crate) sample_freq: f64,
    #[serde(default = "yes")]
    pub(crate) record_enabled: bool,
    #[serde(default)]
    pub(crate) cache_last_msg: bool,
}

/// `playback_actions[i].options`.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PlaybackOptions {
    /// One bag folder, holding `metadata.yaml`.
    pub(crate) bag_path: String,
    pub(crate) mode: String,
    pub(crate) executor: String,
    #[serde(default)]
    pub(crate) skip_duration_s: u64,
    /// 0: to the end.
    #[serde(default)]
    pub(crate) play_duration_s: u64,
    /// The topics to play (all of the bag's when empty).
    #[serde(default)]
    pub(crate) topic_meta_list: Vec<PlayTopicMeta>,
    /// Beyond AimRT: the recorded gaps are divided by this (2: twice as fast).
    #[serde(default = "one")]
    pub(crate) rate: f64,
    /// Beyond AimRT: publish without waiting between messages (`rate` is then unused).
    #[serde(default)]
    pub(crate) as_fast_as_possible: bool,
}

fn one() -> f64 {
    1.0
}

/// `playback_actions[i].options.topic_meta_list[j]`.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PlayTopicMeta {
    pub(crate) topic_name: String,
    pub(crate) msg_type: String,
}
