//! `aimrt-plugin-api`: the one crate that both the `aimrt_main` host and every module or
//! plugin library link.
//!
//! It holds the versioned C ABI ([`ffi`]) and the safe API over it: [`Module`] and
//! [`CoreRef`] for module authors, [`Plugin`], [`Registrar`] and [`Executor`] for plugin
//! authors, and [`ExecutorRef`], [`Task`], [`DynamicLatch`], [`Timer`] and async tasks
//! ([`co`]) for both.
//!
//! # A complete minimal module
//!
//! ```ignore
//! // Cargo.toml: [lib] crate-type = ["cdylib"]; depends on aimrt-plugin-api, serde, tracing
//! use aimrt_plugin_api::{CoreRef, Error, Module, ModuleInfo};
//!
//! #[derive(Default)]
//! pub struct HelloModule;
//!
//! impl Module for HelloModule {
//!     fn info(&self) -> ModuleInfo {
//!         ModuleInfo::new("HelloModule")
//!     }
//!     fn initialize(&mut self, core: CoreRef) -> Result<(), Error> {
//!         let exec = core.executor("work_executor")?;
//!         exec.execute(|| tracing::info!("hello from a task"))?;
//!         Ok(())
//!     }
//! }
//!
//! aimrt_plugin_api::export_modules!(HelloModule);
//! ```
//!
//! # A complete minimal executor plugin
//!
//! ```ignore
//! use std::sync::Arc;
//! use aimrt_plugin_api::{Error, ExecuteError, Executor, Plugin, PluginOptions, Registrar, Task};
//!
//! /// Runs every task inline, on the caller's thread.
//! struct Inline { name: String }
//!
//! impl Executor for Inline {
//!     fn type_name(&self) -> &str { "inline" }
//!     fn name(&self) -> &str { &self.name }
//!     fn thread_safe(&self) -> bool { false }
//!     fn is_in_current_executor(&self) -> bool { false }
//!     fn execute(&self, task: Task) -> Result<(), ExecuteError> {
//!         task.run(&self.name);
//!         Ok(())
//!     }
//!     fn shutdown(&self) {}
//! }
//!
//! #[derive(Default)]
//! struct InlinePlugin;
//!
//! impl Plugin for InlinePlugin {
//!     fn name(&self) -> &str { "inline_plugin" }
//!     fn initialize(&mut self, r: &mut Registrar<'_>, _: &PluginOptions) -> Result<(), Error> {
//!         r.register_executor_type("inline", &[], |args| {
//!             Ok(Arc::new(Inline { name: args.name.to_owned() }))
//!         })
//!     }
//! }
//!
//! pub fn plugin() -> Box<dyn Plugin> { Box::new(InlinePlugin) }
//! aimrt_plugin_api::export_plugin!(plugin);
//! ```

pub mod channel;
pub mod co;
/// Google's well-known protobuf types (`google.protobuf.Timestamp`, `Empty`, the wrappers,
/// …) with the proto3 JSON mapping, each a [`channel::Message`] named
/// `pb:google.protobuf.<Name>` (feature `prost`). Code from `aimrt-codegen` uses them for
/// every `google.protobuf` type a `.proto` file imports.
#[cfg(feature = "prost")]
pub use pbjson_types;
mod control;
mod error;
mod executor;
mod export;
pub mod ffi;
mod file;
mod latch;
mod log;
mod meta;
mod module;
mod panic;
mod parameter;
mod plugin;
mod rate_limit;
#[cfg(feature = "regex")]
mod regex_rule;
pub mod rpc;
mod suggest;
#[cfg(test)]
mod test_util;
mod thread;
mod timer;

pub use crate::control::RuntimeControl;
pub use crate::error::{Error, ExecuteError};
pub use crate::executor::{Executor, ExecutorArgs, ExecutorRef};
pub use crate::ffi::log_backend::{LogBackend, LogEntry};
pub use crate::ffi::task::{Task, TaskOutcome};
pub use crate::ffi::ExecutorStats;
pub use crate::file::read_regular_file;
pub use crate::latch::{DynamicLatch, LatchUnderflow};
pub use crate::log::{rewrite_log_lines, LogLevel, LogLine, LogSink, ParseLevelError};
pub use crate::module::{CoreHost, CoreRef, ExecutorManagerRef, Logger, Module, ModuleInfo};
pub use crate::parameter::ParameterRef;
pub use crate::plugin::{Plugin, PluginOptions, Registrar, TypeSupportPkg, TypeSupports};
pub use crate::rate_limit::RateLimit;
#[cfg(feature = "regex")]
pub use crate::regex_rule::whole_match;
pub use crate::rpc::{
    meta_keys, BackendOptions, HostServices, Responder, RpcBackend, RpcClient, RpcContext,
    RpcContextKind, RpcRef, RpcStatus, ServiceError, ServiceHost,
};
pub use crate::thread::{
    thread_name, ThreadConfigurator, ThreadFactory, ThreadSettingsRef, MAX_THREAD_NUM,
};
pub use crate::timer::{create_timer, Timer};

/// Plumbing for the export macros and the host; not a stable API.
#[doc(hidden)]
pub mod __private {
    pub use crate::ffi::channel::{table_of, type_support, type_support_as_1_4, with_copied_table};
    pub use crate::ffi::library::{
        create_module, create_plugin, create_plugin_as_1_3, module_name, type_support_at,
        DescriptorUpTo12, ModuleCtor,
    };
    pub use crate::ffi::registrar::RegistrarHost;
    pub use crate::log::capture_logs;
    pub use crate::suggest::{closest, did_you_mean, explain, explain_json, no_such, read_options};

    /// `text` with every run of ASCII digits made one `#`: a line the docs show compared
    /// with the one the code writes, numbers aside.
    ///
    /// ```
    /// let text = aimrt_plugin_api::__private::numbers_as_hash("120 sent, 0 lost");
    /// assert_eq!(text, "# sent, # lost");
    /// ```
    pub fn numbers_as_hash(text: &str) -> String {
        let mut out = String::with_capacity(text.len());
        for c in text.chars() {
            if !c.is_ascii_digit() {
                out.push(c);
            } else if !out.ends_with('#') {
                out.push('#');
            }
        }
        out
    }

    /// The `<label> <hex>` lines of a wire fixture (`#` starts a comment), as bytes, for
    /// the golden tests of every crate that reads `tests/fixtures/aimrt-wire/`.
    ///
    /// ```
    /// let lines = aimrt_plugin_api::__private::hex_lines("# x\nframe 0a0b\n");
    /// assert_eq!(lines, [("frame".to_owned(), vec![10, 11])]);
    /// ```
    pub fn hex_lines(text: &str) -> Vec<(String, Vec<u8>)> {
        text.lines()
            .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
            .map(|l| {
                let (label, hex) = l.split_once(' ').unwrap_or((l, ""));
                let hex: String = hex.split_whitespace().collect();
                let bytes = (0..hex.len() / 2)
                    .filter_map(|i| u8::from_str_radix(hex.get(2 * i..2 * i + 2)?, 16).ok())
                    .collect();
                (label.to_owned(), bytes)
            })
            .collect()
    }

    /// `bytes` damaged every way the decoders' tests try, each with what was done: every
    /// byte flipped, and at every offset where it fits a 16-, 32- or 64-bit length that
    /// no input holds (all ones, half the range, 2^40, just over 256 MiB, 1 MiB, zero),
    /// little-endian as every format here writes them.
    ///
    /// ```
    /// let all: Vec<_> = aimrt_plugin_api::__private::damaged(&[1, 2]).collect();
    /// assert!(all.iter().any(|(what, b)| what == "byte 0 flipped" && b[..] == [0xfe, 2]));
    /// assert!(all.iter().any(|(_, b)| b[..] == [0xff, 0xff]));
    /// ```
    pub fn damaged(bytes: &[u8]) -> impl Iterator<Item = (String, Vec<u8>)> + '_ {
        let u64s = [u64::MAX, 1 << 40, 1 << 31, (1 << 28) + 1, 1 << 20, 0];
        let patches: Vec<Vec<u8>> = [u16::MAX.to_le_bytes().to_vec()]
            .into_iter()
            .chain([u32::MAX, 0x8000_0000].map(|v| v.to_le_bytes().to_vec()))
            .chain(u64s.map(|v| v.to_le_bytes().to_vec()))
            .collect();
        let flips = (0..bytes.len()).map(move |at| {
            let mut d = bytes.to_vec();
            d[at] ^= 0xff;
            (format!("byte {at} flipped"), d)
        });
        let lengths = patches.into_iter().flat_map(move |patch| {
            let n = patch.len();
            (0..(bytes.len() + 1).saturating_sub(n)).map(move |at| {
                let mut d = bytes.to_vec();
                d[at..at + n].copy_from_slice(&patch);
                (format!("{patch:02x?} at {at}"), d)
            })
        });
        flips.chain(lengths)
    }

    /// Runs `read` on every damaged variant ([`damaged`]) of every capture in the wire
    /// fixture `files` (read by [`hex_lines`]) in `dir`, and returns how many it ran. A
    /// panic in `read` fails with the file, the capture and the damage that caused it.
    pub fn read_damaged_captures(dir: &str, files: &[&str], read: impl Fn(&[u8])) -> usize {
        let mut tried = 0;
        for file in files {
            let path = format!("{dir}/{file}");
            let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
            for (label, bytes) in hex_lines(&text) {
                for (what, d) in damaged(&bytes) {
                    let read = std::panic::AssertUnwindSafe(&read);
                    if let Err(e) = std::panic::catch_unwind(|| read(&d)) {
                        panic!("{file} {label}, {what}: {e:?}");
                    }
                    tried += 1;
                }
            }
        }
        tried
    }

    /// After the host changed a logger's level: has this library's `tracing` read the
    /// levels again, so lines of a newly enabled level are no longer skipped. Levels are
    /// read when a library's loggers are added; the runtime calls this for its own
    /// loggers and sets every level before it loads any library.
    pub fn levels_changed() {
        crate::ffi::context::levels_changed();
    }

    /// The host's own setup: its log lines outside any module go to `core_logger`, and
    /// panics become log lines. Static registration relies on this instead of a library
    /// entry.
    pub fn install_host(core_logger: crate::ffi::RawLogger) {
        crate::ffi::context::set_default_logger(core_logger);
        crate::panic::install_hook();
        crate::log::install_forwarder();
    }

    /// A service object as the registrar would receive it (host-side tests).
    pub fn service<F>(handler: F) -> crate::ffi::RawService
    where
        F: Fn(&str, &[u8]) -> Result<Vec<u8>, crate::ServiceError> + Send + Sync + 'static,
    {
        crate::ffi::RawService::new(handler)
    }

    /// Runs `f`, turning a panic into `Err(message)`.
    pub fn contain<R>(f: impl FnOnce() -> R) -> Result<R, String> {
        crate::panic::contain(f)
    }

    pub use crate::panic::HelperFailed;

    /// Runs `f` on a helper thread, its panic contained, waiting at most `limit`: for
    /// work in a dependency that may hang instead of failing.
    pub fn contain_on_helper<R: Send + 'static>(
        name: &str,
        limit: std::time::Duration,
        f: impl FnOnce() -> R + Send + 'static,
    ) -> Result<R, HelperFailed> {
        crate::panic::contain_on_helper(name, limit, f)
    }

    /// Name of the module whose code runs on this thread, if any.
    pub fn current_module_name() -> Option<&'static str> {
        crate::ffi::context::current_module_name()
    }
}
