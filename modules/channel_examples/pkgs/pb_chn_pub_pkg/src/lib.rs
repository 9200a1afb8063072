//! `libpb_chn_pub_pkg.so`: the publishers of AimRT's two-pkg channel examples.

use aimrt_channel_examples::{BenchmarkPublisherModule, NormalPublisherModule};

aimrt_plugin_api::export_modules!(NormalPublisherModule, BenchmarkPublisherModule);
