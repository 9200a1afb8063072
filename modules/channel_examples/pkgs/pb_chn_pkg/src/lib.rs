//! `libpb_chn_pkg.so`: every channel example module in one pkg (AimRT's single-pkg examples).

use aimrt_channel_examples::{
    AsyncSubscriberModule, BenchmarkPublisherModule, BenchmarkSubscriberModule,
    NormalPublisherModule, NormalSubscriberModule, RelayModule,
};

aimrt_plugin_api::export_modules!(
    NormalPublisherModule,
    NormalSubscriberModule,
    AsyncSubscriberModule,
    RelayModule,
    BenchmarkPublisherModule,
    BenchmarkSubscriberModule
);
