//! The module vtable (library → host), its exporter and importer.

use std::ffi::c_void;

use super::context::{self, ModuleCtx};
use super::core::RawCore;
use super::plugin::report;
use super::{contain, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::module::{CoreRef, Module, ModuleInfo};

/// Module information as it crosses the ABI (views valid as long as the module).
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawModuleInfo {
    /// Size and minor of this struct.
    pub header: Header,
    /// The module name (required, unique in the process).
    pub name: StrView,
    /// Version, major.
    pub major_version: u32,
    /// Version, minor.
    pub minor_version: u32,
    /// Version, patch.
    pub patch_version: u32,
    /// Version, build.
    pub build_version: u32,
    /// Author.
    pub author: StrView,
    /// Description.
    pub description: StrView,
}

impl RawModuleInfo {
    pub(crate) fn of(info: &ModuleInfo) -> RawModuleInfo {
        RawModuleInfo {
            header: Header::of::<RawModuleInfo>(),
            name: StrView::new(&info.name),
            major_version: info.major_version,
            minor_version: info.minor_version,
            patch_version: info.patch_version,
            build_version: info.build_version,
            author: StrView::new(&info.author),
            description: StrView::new(&info.description),
        }
    }

    /// Copies the info out.
    ///
    /// # Safety
    /// The views must be readable.
    pub(crate) unsafe fn to_info(self) -> ModuleInfo {
        // SAFETY: forwarded to the caller.
        unsafe {
            ModuleInfo {
                name: self.name.to_string_lossy(),
                major_version: self.major_version,
                minor_version: self.minor_version,
                patch_version: self.patch_version,
                build_version: self.build_version,
                author: self.author.to_string_lossy(),
                description: self.description.to_string_lossy(),
            }
        }
    }

    pub(crate) const fn empty() -> RawModuleInfo {
        RawModuleInfo {
            header: Header::of::<RawModuleInfo>(),
            name: StrView::EMPTY,
            major_version: 0,
            minor_version: 0,
            patch_version: 0,
            build_version: 0,
            author: StrView::EMPTY,
            description: StrView::EMPTY,
        }
    }
}

/// A module object and its operations.
#[repr(C)]
pub struct RawModule {
    /// The operations.
    pub vtable: *const ModuleVtable,
    /// The module.
    pub obj: *mut c_void,
}

// SAFETY: modules are `Send` (required by the exporter); the host calls one at a time.
unsafe impl Send for RawModule {}

/// Module operations.
#[repr(C)]
pub struct ModuleVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Writes the module's info (constant for its lifetime).
    pub info: unsafe extern "C" fn(obj: *mut c_void, out: *mut RawModuleInfo),
    /// Initializes with the module's core handle (valid for the process's life).
    pub initialize: unsafe extern "C" fn(obj: *mut c_void, core: RawCore, err: ErrorSink) -> Status,
    /// Starts.
    pub start: unsafe extern "C" fn(obj: *mut c_void, err: ErrorSink) -> Status,
    /// Shuts down.
    pub shutdown: unsafe extern "C" fn(obj: *mut c_void),
    /// Frees the module.
    pub destroy: unsafe extern "C" fn(obj: *mut c_void),
}

struct ModuleObj {
    module: Box<dyn Module>,
    info: ModuleInfo,
    ctx: Option<&'static ModuleCtx>,
}

impl ModuleObj {
    const VTABLE: ModuleVtable = ModuleVtable {
        header: Header::of::<ModuleVtable>(),
        info: Self::info,
        initialize: Self::initialize,
        start: Self::start,
        shutdown: Self::shutdown,
        destroy: Self::destroy,
    };

    /// # Safety
    /// `obj` comes from `RawModule::new` and was not destroyed; no other reference is live.
    unsafe fn get<'a>(obj: *mut c_void) -> &'a mut ModuleObj {
        // SAFETY: per the contract.
        unsafe { &mut *obj.cast::<ModuleObj>() }
    }

    unsafe extern "C" fn info(obj: *mut c_void, out: *mut RawModuleInfo) {
        // SAFETY: live module (vtable contract).
        let this = unsafe { Self::get(obj) };
        // SAFETY: `out` is writable; the views point into `this.info`, which lives as long
        // as the module.
        unsafe { out.write(RawModuleInfo::of(&this.info)) }
    }

    unsafe extern "C" fn initialize(obj: *mut c_void, core: RawCore, err: ErrorSink) -> Status {
        // SAFETY: live module.
        let this = unsafe { Self::get(obj) };
        // SAFETY: the host passes its own leaked core handle (vtable contract).
        let core = unsafe { CoreRef::from_raw(core) };
        let ctx = *this
            .ctx
            .get_or_insert_with(|| context::new_module(this.info.name.clone(), core.raw_logger()));
        let module = &mut this.module;
        report(
            context::with_module(ctx, || contain(|| module.initialize(core))),
            "initialize",
            err,
        )
    }

    unsafe extern "C" fn start(obj: *mut c_void, err: ErrorSink) -> Status {
        // SAFETY: live module.
        let this = unsafe { Self::get(obj) };
        let module = &mut this.module;
        report(
            in_ctx(this.ctx, || contain(|| module.start())),
            "start",
            err,
        )
    }

    unsafe extern "C" fn shutdown(obj: *mut c_void) {
        // SAFETY: live module.
        let this = unsafe { Self::get(obj) };
        let name = this.info.name.clone();
        let module = &mut this.module;
        in_ctx(this.ctx, || {
            if let Err(panic) = contain(|| module.shutdown()) {
                tracing::error!(target: "aimrt", "module '{name}' panicked in shutdown: {panic}");
            }
        });
    }

    unsafe extern "C" fn destroy(obj: *mut c_void) {
        // SAFETY: called once, last; pointer from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast::<ModuleObj>()) };
        let _ = in_ctx(b.ctx, || contain(move || drop(b)));
    }
}

/// Runs `f` inside the module's context when it has one (after `initialize`).
fn in_ctx<R>(ctx: Option<&'static ModuleCtx>, f: impl FnOnce() -> R) -> R {
    match ctx {
        Some(ctx) => context::with_module(ctx, f),
        None => f(),
    }
}

impl RawModule {
    /// Exports a module (used by `export_modules!` and by app mode). Calls `info()` once;
    /// a panic there is an error.
    pub fn new(module: Box<dyn Module>) -> Result<RawModule, String> {
        let info =
            contain(|| module.info()).map_err(|p| format!("module panicked in info(): {p}"))?;
        Ok(RawModule {
            vtable: &ModuleObj::VTABLE,
            obj: Box::into_raw(Box::new(ModuleObj {
                module,
                info,
                ctx: None,
            }))
            .cast(),
        })
    }

    fn vt(&self) -> &ModuleVtable {
        // SAFETY: module vtables are `'static` (libraries are never unloaded).
        unsafe { &*self.vtable }
    }

    /// The module's info (host use).
    pub fn info(&self) -> ModuleInfo {
        let mut out = RawModuleInfo::empty();
        // SAFETY: live module; `out` is writable; views are copied before returning.
        unsafe {
            (self.vt().info)(self.obj, &mut out);
            out.to_info()
        }
    }

    /// Calls `initialize` (host use).
    pub fn initialize(&mut self, core: RawCore) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live module; the sink outlives the call.
        let status = unsafe { (self.vt().initialize)(self.obj, core, slot.sink()) };
        slot.result(status)
    }

    /// Calls `start` (host use).
    pub fn start(&mut self) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live module; the sink outlives the call.
        let status = unsafe { (self.vt().start)(self.obj, slot.sink()) };
        slot.result(status)
    }

    /// Calls `shutdown` (host use).
    pub fn shutdown(&mut self) {
        // SAFETY: live module.
        unsafe { (self.vt().shutdown)(self.obj) }
    }
}

impl Drop for RawModule {
    fn drop(&mut self) {
        // SAFETY: we own the module; this is its last use.
        unsafe { (self.vt().destroy)(self.obj) }
    }
}
