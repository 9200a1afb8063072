//! The core handle (host → module): one per module, valid for the process's life.

use std::ffi::c_void;
use std::sync::Arc;

use super::executor::RawExecutor;
use super::logger::RawLogger;
use super::module::RawModuleInfo;
use super::{contain, Header, Status, StrView};
use crate::module::CoreHost;

/// A module's handle to the runtime.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawCore {
    /// The operations.
    pub vtable: *const CoreVtable,
    /// The host's object.
    pub obj: *const c_void,
}

// SAFETY: core objects are `Send + Sync` (required by the exporter) and never freed.
unsafe impl Send for RawCore {}
// SAFETY: see `Send`.
unsafe impl Sync for RawCore {}

/// The channel handle of a module. Its operations are appended by the channel feature
/// (ABI 1.1); a module reads them only when `header.size` says they are there.
#[repr(C)]
pub struct ChannelHandleVtable {
    /// Size and minor of this table.
    pub header: Header,
}

/// Core operations.
#[repr(C)]
pub struct CoreVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The module's info as the runtime knows it.
    pub info: unsafe extern "C" fn(obj: *const c_void, out: *mut RawModuleInfo),
    /// AimRT's `GetConfigFilePath()`: `modules[i].cfg_file_path`, else the temp file the
    /// runtime wrote from the root node named after the module, else empty.
    pub config_file_path: unsafe extern "C" fn(obj: *const c_void) -> StrView,
    /// The module's root config node as JSON (`null` when absent).
    pub config_json: unsafe extern "C" fn(obj: *const c_void) -> StrView,
    /// Looks up an executor by name; `NOT_FOUND` if there is none.
    pub get_executor:
        unsafe extern "C" fn(obj: *const c_void, name: StrView, out: *mut RawExecutor) -> Status,
    /// The module's logger (named after it, at its level).
    pub logger: unsafe extern "C" fn(obj: *const c_void) -> RawLogger,
    /// The module's channel handle; `UNSUPPORTED` until the channel feature.
    pub channel:
        unsafe extern "C" fn(obj: *const c_void, out: *mut *const ChannelHandleVtable) -> Status,
}

struct Export<C>(C);

impl<C: CoreHost> Export<C> {
    const VTABLE: CoreVtable = CoreVtable {
        header: Header::of::<CoreVtable>(),
        info: Self::info,
        config_file_path: Self::config_file_path,
        config_json: Self::config_json,
        get_executor: Self::get_executor,
        logger: Self::logger,
        channel: Self::channel,
    };

    /// # Safety
    /// `obj` is the leaked `Arc<C>` of `RawCore::leak::<C>`.
    unsafe fn get<'a>(obj: *const c_void) -> &'a C {
        // SAFETY: per the contract; never freed.
        unsafe { &*obj.cast::<C>() }
    }

    unsafe extern "C" fn info(obj: *const c_void, out: *mut RawModuleInfo) {
        // SAFETY: live core (never freed).
        let c = unsafe { Self::get(obj) };
        // SAFETY: `out` is writable; the views point into the core, which lives forever.
        unsafe { out.write(RawModuleInfo::of(c.info())) }
    }

    unsafe extern "C" fn config_file_path(obj: *const c_void) -> StrView {
        // SAFETY: live core.
        let c = unsafe { Self::get(obj) };
        StrView::new(c.config_file_path())
    }

    unsafe extern "C" fn config_json(obj: *const c_void) -> StrView {
        // SAFETY: live core.
        let c = unsafe { Self::get(obj) };
        StrView::new(c.config_json())
    }

    unsafe extern "C" fn get_executor(
        obj: *const c_void,
        name: StrView,
        out: *mut RawExecutor,
    ) -> Status {
        // SAFETY: live core.
        let c = unsafe { Self::get(obj) };
        // SAFETY: the view is valid for this call.
        let name = unsafe { name.to_string_lossy() };
        match contain(|| c.executor(&name)) {
            Ok(Some(e)) => {
                // SAFETY: `out` is writable.
                unsafe { out.write(e) };
                Status::OK
            }
            Ok(None) => Status::NOT_FOUND,
            Err(_) => Status::FAILED,
        }
    }

    unsafe extern "C" fn logger(obj: *const c_void) -> RawLogger {
        // SAFETY: live core.
        let c = unsafe { Self::get(obj) };
        c.logger()
    }

    unsafe extern "C" fn channel(_: *const c_void, _: *mut *const ChannelHandleVtable) -> Status {
        Status::UNSUPPORTED
    }
}

impl RawCore {
    /// Exports a core handle; leaked, as modules may keep it (in tasks) for the process's life.
    pub fn leak<C: CoreHost>(core: Arc<C>) -> RawCore {
        RawCore {
            vtable: &Export::<C>::VTABLE,
            obj: Arc::into_raw(core).cast(),
        }
    }

    fn vt(&self) -> &CoreVtable {
        // SAFETY: core vtables are `'static` and core objects are never freed.
        unsafe { &*self.vtable }
    }

    pub(crate) fn info(&self) -> crate::ModuleInfo {
        let mut out = RawModuleInfo::empty();
        // SAFETY: live core; views copied before returning.
        unsafe {
            (self.vt().info)(self.obj, &mut out);
            out.to_info()
        }
    }

    pub(crate) fn config_file_path(&self) -> String {
        // SAFETY: live core; copied at once.
        unsafe { (self.vt().config_file_path)(self.obj).to_string_lossy() }
    }

    pub(crate) fn config_json(&self) -> String {
        // SAFETY: live core; copied at once.
        unsafe { (self.vt().config_json)(self.obj).to_string_lossy() }
    }

    pub(crate) fn executor(&self, name: &str) -> Option<RawExecutor> {
        let mut out = RawExecutor::null();
        // SAFETY: live core; `out` is writable.
        let status = unsafe { (self.vt().get_executor)(self.obj, StrView::new(name), &mut out) };
        (status.is_ok() && !out.is_null()).then_some(out)
    }

    pub(crate) fn logger(&self) -> RawLogger {
        // SAFETY: live core.
        unsafe { (self.vt().logger)(self.obj) }
    }
}
