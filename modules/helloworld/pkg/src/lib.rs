//! `libhelloworld_pkg.so`: AimRT's hello world module package (`HelloWorldModule`).

use aimrt_helloworld::HelloWorldModule;

aimrt_plugin_api::export_modules!(HelloWorldModule);
