//! The one entry of every library: a static descriptor the host reads before running any
//! of the library's code, and the library-wide initialisation that follows.

use super::context;
use super::module::RawModule;
use super::plugin::RawPlugin;
use super::{
    padded, ErrorSink, Header, RawLogger, Status, StrView, ABI_MAJOR, ABI_MINOR, API_VERSION,
    MAGIC, TARGET,
};
use crate::module::Module;
use crate::plugin::Plugin;

/// What the host hands a library once, before anything else.
#[repr(C)]
pub struct HostInit {
    /// Size and minor of this struct.
    pub header: Header,
    /// Where lines logged outside any module go (named after the library).
    pub library_logger: RawLogger,
}

/// The exported entry of a library (symbol [`ENTRY_SYMBOL`](super::ENTRY_SYMBOL)).
///
/// The first five fields are frozen for every ABI major: the host reads them to decide
/// whether it may read the rest.
#[repr(C)]
pub struct LibraryDescriptor {
    /// [`MAGIC`].
    pub magic: u64,
    /// ABI major the library was built against.
    pub abi_major: u32,
    /// ABI minor the library was built against.
    pub abi_minor: u32,
    /// `size_of::<LibraryDescriptor>()` as the library compiled it.
    pub size: u32,
    /// 1 if the library unwinds on panic (`panic = "unwind"`), 0 if it aborts.
    pub unwind: u32,
    /// `aimrt-plugin-api` version, NUL-padded.
    pub api_version: [u8; 32],
    /// Target triple, NUL-padded.
    pub target: [u8; 64],
    /// Library-wide setup: panic hook and log forwarder. Called once, first.
    pub init: Option<unsafe extern "C" fn(host: *const HostInit) -> Status>,
    /// Number of modules this library exports.
    pub module_count: Option<unsafe extern "C" fn() -> usize>,
    /// Name of the `index`-th module (static).
    pub module_name: Option<unsafe extern "C" fn(index: usize) -> StrView>,
    /// Creates the named module.
    pub create_module:
        Option<unsafe extern "C" fn(name: StrView, out: *mut RawModule, err: ErrorSink) -> Status>,
    /// Creates the library's plugin.
    pub create_plugin: Option<unsafe extern "C" fn(out: *mut RawPlugin, err: ErrorSink) -> Status>,
}

impl LibraryDescriptor {
    /// A descriptor of this crate's ABI with no exports; the macros fill in the entries.
    pub const fn new(unwind: bool) -> LibraryDescriptor {
        LibraryDescriptor {
            magic: MAGIC,
            abi_major: ABI_MAJOR,
            abi_minor: ABI_MINOR,
            size: size_of::<LibraryDescriptor>() as u32,
            unwind: unwind as u32,
            api_version: padded(API_VERSION),
            target: padded(TARGET),
            init: Some(init_library),
            module_count: None,
            module_name: None,
            create_module: None,
            create_plugin: None,
        }
    }
}

/// The `init` entry of every library descriptor.
///
/// # Safety
/// `host` points to a valid [`HostInit`] for the call.
pub(crate) unsafe extern "C" fn init_library(host: *const HostInit) -> Status {
    // SAFETY: per the contract.
    let host = unsafe { &*host };
    context::set_default_logger(host.library_logger);
    crate::panic::install_hook();
    crate::log::install_forwarder();
    Status::OK
}

/// A module constructor listed by `export_modules!`.
pub type ModuleCtor = fn() -> Box<dyn Module>;

/// `module_name` for a static list.
pub fn module_name(list: &'static [(&'static str, ModuleCtor)], index: usize) -> StrView {
    list.get(index)
        .map_or(StrView::EMPTY, |(n, _)| StrView::new(n))
}

/// `create_module` for a static list.
///
/// # Safety
/// `name` is valid for the call and `out` is writable.
pub unsafe fn create_module(
    list: &'static [(&'static str, ModuleCtor)],
    name: StrView,
    out: *mut RawModule,
    err: ErrorSink,
) -> Status {
    // SAFETY: per the contract.
    let name = unsafe { name.to_string_lossy() };
    let Some((_, ctor)) = list.iter().find(|(n, _)| *n == name) else {
        err.report(&format!("this library has no module '{name}'"));
        return Status::NOT_FOUND;
    };
    let made =
        super::contain(ctor).map_err(|p| format!("constructor of module '{name}' panicked: {p}"));
    match made.and_then(RawModule::new) {
        Ok(m) => {
            // SAFETY: `out` is writable per the contract.
            unsafe { out.write(m) };
            Status::OK
        }
        Err(e) => {
            err.report(&e);
            Status::FAILED
        }
    }
}

/// `create_plugin` for a constructor.
///
/// # Safety
/// `out` is writable.
pub unsafe fn create_plugin(
    ctor: fn() -> Box<dyn Plugin>,
    out: *mut RawPlugin,
    err: ErrorSink,
) -> Status {
    match super::contain(ctor) {
        Ok(p) => {
            // SAFETY: per the contract.
            unsafe { out.write(RawPlugin::new(p)) };
            Status::OK
        }
        Err(panic) => {
            err.report(&format!("plugin constructor panicked: {panic}"));
            Status::FAILED
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::mem::offset_of;

    #[test]
    fn frozen_prefix_layout() {
        assert_eq!(offset_of!(LibraryDescriptor, magic), 0);
        assert_eq!(offset_of!(LibraryDescriptor, abi_major), 8);
        assert_eq!(offset_of!(LibraryDescriptor, abi_minor), 12);
        assert_eq!(offset_of!(LibraryDescriptor, size), 16);
        assert_eq!(offset_of!(LibraryDescriptor, unwind), 20);
        assert_eq!(offset_of!(LibraryDescriptor, api_version), 24);
        assert_eq!(offset_of!(LibraryDescriptor, target), 56);
        assert_eq!(offset_of!(LibraryDescriptor, init), 120);
    }

    #[test]
    fn new_descriptor_describes_this_crate() {
        let d = LibraryDescriptor::new(true);
        assert_eq!(d.magic, MAGIC);
        assert_eq!((d.abi_major, d.abi_minor), (ABI_MAJOR, ABI_MINOR));
        assert_eq!(d.size as usize, size_of::<LibraryDescriptor>());
        assert_eq!(super::super::unpad(&d.api_version), API_VERSION);
        assert_eq!(super::super::unpad(&d.target), TARGET);
    }
}
