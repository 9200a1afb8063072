//! The one entry of every library: a static descriptor the host reads before running any
//! of the library's code, and the library-wide initialisation that follows.

use super::context;
use super::module::RawModule;
use super::plugin::RawPlugin;
use super::{
    padded, ErrorSink, Header, RawLogger, Status, StrView, TypeSupportVtable, ABI_MAJOR, ABI_MINOR,
    API_VERSION, MAGIC, TARGET,
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
/// whether it may read the rest. Fields are appended in later minors; the host reads one
/// only when `size` covers it ([`LibraryDescriptor::SIZE_1_2`] is the smallest it takes).
#[repr(C)]
#[derive(Clone, Copy)]
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
    /// (1.3) Number of message types the library offers as a type support package.
    pub type_support_count: Option<unsafe extern "C" fn() -> usize>,
    /// (1.3) The `index`-th type support table (static), or null.
    pub type_support: Option<unsafe extern "C" fn(index: usize) -> *const TypeSupportVtable>,
}

impl LibraryDescriptor {
    /// The size of a descriptor of ABI 1.0 to 1.2 (everything up to `create_plugin`): the
    /// smallest the host accepts.
    pub const SIZE_1_2: usize = std::mem::offset_of!(LibraryDescriptor, type_support_count);

    /// A descriptor with every entry empty (what the host reads past a smaller `size`).
    pub const fn empty() -> LibraryDescriptor {
        LibraryDescriptor {
            magic: 0,
            abi_major: 0,
            abi_minor: 0,
            size: 0,
            unwind: 0,
            api_version: [0; 32],
            target: [0; 64],
            init: None,
            module_count: None,
            module_name: None,
            create_module: None,
            create_plugin: None,
            type_support_count: None,
            type_support: None,
        }
    }

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
            ..LibraryDescriptor::empty()
        }
    }
}

/// The descriptor as ABI 1.0 to 1.2 laid it out (everything up to `create_plugin`), for
/// tests that must load a library of an older minor exactly as it was built.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct DescriptorUpTo12 {
    magic: u64,
    abi_major: u32,
    abi_minor: u32,
    size: u32,
    unwind: u32,
    api_version: [u8; 32],
    target: [u8; 64],
    init: Option<unsafe extern "C" fn(host: *const HostInit) -> Status>,
    module_count: Option<unsafe extern "C" fn() -> usize>,
    module_name: Option<unsafe extern "C" fn(index: usize) -> StrView>,
    create_module:
        Option<unsafe extern "C" fn(name: StrView, out: *mut RawModule, err: ErrorSink) -> Status>,
    create_plugin: Option<unsafe extern "C" fn(out: *mut RawPlugin, err: ErrorSink) -> Status>,
}

// SAFETY: immutable static data (function pointers and integers).
unsafe impl Sync for DescriptorUpTo12 {}

impl DescriptorUpTo12 {
    /// `d` cut to the 1.2 layout, declaring `minor` (≤ 2).
    pub const fn of(d: LibraryDescriptor, minor: u32) -> DescriptorUpTo12 {
        DescriptorUpTo12 {
            magic: d.magic,
            abi_major: d.abi_major,
            abi_minor: minor,
            size: LibraryDescriptor::SIZE_1_2 as u32,
            unwind: d.unwind,
            api_version: d.api_version,
            target: d.target,
            init: d.init,
            module_count: d.module_count,
            module_name: d.module_name,
            create_module: d.create_module,
            create_plugin: d.create_plugin,
        }
    }
}

/// `type_support` for a static list of tables.
pub fn type_support_at(
    list: &'static [fn() -> &'static TypeSupportVtable],
    index: usize,
) -> *const TypeSupportVtable {
    list.get(index)
        .map_or(std::ptr::null(), |f| f() as *const TypeSupportVtable)
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

/// [`create_plugin`] handing the plugin over behind a 1.3 table, in a library that declares
/// 1.3 (`__export_plugin_as_1_3!`, for fixtures).
///
/// # Safety
/// As [`create_plugin`].
#[doc(hidden)]
pub unsafe fn create_plugin_as_1_3(
    ctor: fn() -> Box<dyn Plugin>,
    out: *mut RawPlugin,
    err: ErrorSink,
) -> Status {
    // SAFETY: per the contract.
    let status = unsafe { create_plugin(ctor, out, err) };
    if status.is_ok() {
        // SAFETY: `create_plugin` wrote a plugin there; it is moved out and its
        // replacement written back (`as_1_3` takes over the object).
        unsafe { out.write(out.read().as_1_3()) };
    }
    status
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
        // 1.0–1.2 end after create_plugin; 1.3 appends the type support entries.
        assert_eq!(LibraryDescriptor::SIZE_1_2, 160);
        assert_eq!(offset_of!(LibraryDescriptor, type_support), 168);
        assert_eq!(size_of::<LibraryDescriptor>(), 176);
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
