//! `libpb_chn_pub_pkg.so`: the publisher of AimRT's two-pkg channel example.

use aimrt_channel_examples::NormalPublisherModule;

aimrt_plugin_api::export_modules!(NormalPublisherModule);
