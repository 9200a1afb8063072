//! `aimrt-runtime`: the aimrt-rs host library behind `aimrt_main`.
//!
//! It reads one YAML file (AimRT's key names), loads plugins and module packages from
//! shared libraries through the C ABI of `aimrt-plugin-api`, builds the named executors,
//! runs the module lifecycle and shuts everything down in reverse order.
//!
//! ```no_run
//! use aimrt_runtime::{Runtime, RuntimeOptions};
//! let mut runtime = Runtime::new(RuntimeOptions {
//!     cfg_file_path: Some("config/demo.yaml".into()),
//!     running_duration: Some(std::time::Duration::from_secs(2)),
//!     ..Default::default()
//! });
//! // runtime.builtin_plugin(aimrt_std_executors::plugin());
//! runtime.run().expect("runtime failed");
//! ```
#![deny(unsafe_code)]

mod app;
mod channel;
mod cli;
mod config;
mod control;
mod error;
mod executor;
mod filters;
mod limits;
mod log;
mod module;
mod parameter;
mod plugin;
mod report;
mod routing;
mod rpc;
mod runtime;
mod signals;
mod thread;

pub use crate::app::{App, SpinDuration, SpinError, Spinner};
pub use crate::cli::{parse_args, say, say_err, usage, Cli, CliAction, VERSION};
pub use crate::config::check_config;
pub use crate::error::Error;
pub use crate::limits::{no_library_backtraces, raise_open_file_limit};
pub use crate::runtime::{Runtime, RuntimeOptions, ShutdownHandle};
pub use crate::signals::on_signals;
