//! `libexample_pb_ts.so`: AimRT's example messages as a type support package
//! (`type_support_pkgs[i].path` of echo_plugin and record_playback_plugin).
#![deny(unsafe_code)]

use aimrt_protocols::example::{
    ExampleEventMsg, GetBarDataReq, GetBarDataRsp, GetFooDataReq, GetFooDataRsp,
};

aimrt_plugin_api::export_type_support!(
    ExampleEventMsg,
    GetFooDataReq,
    GetFooDataRsp,
    GetBarDataReq,
    GetBarDataRsp
);
