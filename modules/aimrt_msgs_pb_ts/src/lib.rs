//! `libaimrt_msgs_pb_ts.so`: AimRT's common robot messages (`aimrt.protocols.common`,
//! `geometry` and `sensor`), and the `LogData` that topic_logger_plugin publishes, as a
//! type support package (`type_support_pkgs[i].path` of
//! echo_plugin and record_playback_plugin), so the topics of an AimRT robot can be echoed
//! and recorded by name.
#![deny(unsafe_code)]

use aimrt_protocols::common::{Error, Header, ModuleException, ModuleStatus};
use aimrt_protocols::geometry::{Quaternion, Vector3};
use aimrt_protocols::sensor::{
    CompressedImage, ImuState, JointState, JointStateArray, TouchSensorState, TouchSensorStateArray,
};
use aimrt_protocols::topic_logger::LogData;

aimrt_plugin_api::export_type_support!(
    Header,
    Error,
    ModuleStatus,
    ModuleException,
    Quaternion,
    Vector3,
    ImuState,
    CompressedImage,
    JointState,
    JointStateArray,
    TouchSensorState,
    TouchSensorStateArray,
    LogData
);
