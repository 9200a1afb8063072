//! `libpb_chn_pkg.so`: every channel example module in one pkg (AimRT's single-pkg example).

use aimrt_channel_examples::{
    AsyncSubscriberModule, NormalPublisherModule, NormalSubscriberModule, RelayModule,
};

aimrt_plugin_api::export_modules!(
    NormalPublisherModule,
    NormalSubscriberModule,
    AsyncSubscriberModule,
    RelayModule
);
