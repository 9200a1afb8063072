//! `record_playback_plugin`, exported from `libaimrt_record_playback_plugin.so`.
#![deny(unsafe_code)]

aimrt_plugin_api::export_plugin!(aimrt_record_playback::plugin);
