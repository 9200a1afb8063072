//! `libpb_chn_sub_pkg.so`: the subscribers of AimRT's two-pkg channel examples.

use aimrt_channel_examples::{
    AsyncSubscriberModule, BenchmarkSubscriberModule, NormalSubscriberModule, RelayModule,
};

aimrt_plugin_api::export_modules!(
    NormalSubscriberModule,
    AsyncSubscriberModule,
    RelayModule,
    BenchmarkSubscriberModule
);
