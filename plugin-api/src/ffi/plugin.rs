//! The plugin vtable (library → host), its exporter and importer.

use std::ffi::c_void;

use super::registrar::{RawRegistrar, RegistrarHost};
use super::{contain, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::plugin::{Plugin, PluginOptions, Registrar};

/// Arguments of a plugin's `init`.
#[repr(C)]
pub struct PluginInitArgs {
    /// Size and minor of this struct.
    pub header: Header,
    /// Where to register contributions; valid during `init` only.
    pub registrar: RawRegistrar,
    /// The plugin's `options` node as JSON text (`null` when absent).
    pub options_json: StrView,
    /// Where the options are, `file:line:col`.
    pub location: StrView,
}

/// A plugin object and its operations.
#[repr(C)]
pub struct RawPlugin {
    /// The operations.
    pub vtable: *const PluginVtable,
    /// The plugin.
    pub obj: *mut c_void,
}

// SAFETY: plugins are `Send` (required by the exporter) and the host calls them from one
// thread at a time.
unsafe impl Send for RawPlugin {}

/// Plugin operations.
#[repr(C)]
pub struct PluginVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The plugin's name; must equal `plugins[i].name`. Valid until `destroy`.
    pub name: unsafe extern "C" fn(obj: *mut c_void) -> StrView,
    /// Reads options and registers contributions.
    pub init: unsafe extern "C" fn(
        obj: *mut c_void,
        args: *const PluginInitArgs,
        err: ErrorSink,
    ) -> Status,
    /// Called after modules initialized, before they start.
    pub start: unsafe extern "C" fn(obj: *mut c_void, err: ErrorSink) -> Status,
    /// Called after modules and channels shut down.
    pub shutdown: unsafe extern "C" fn(obj: *mut c_void),
    /// Frees the plugin.
    pub destroy: unsafe extern "C" fn(obj: *mut c_void),
    /// (1.4) Called once everything has started, modules included (AimRT's kPostStart);
    /// read only when `header.size` covers it.
    pub post_start: Option<unsafe extern "C" fn(obj: *mut c_void)>,
}

impl PluginVtable {
    /// The size of a plugin table of ABI 1.0 to 1.3 (everything up to `destroy`).
    pub const SIZE_1_3: usize = std::mem::offset_of!(PluginVtable, post_start);
}

/// A plugin table in the layout of ABI 1.0 to 1.3: what the host reads of every table, and
/// what `__export_plugin_as_1_3!` exports for the fixture that proves older plugins load.
#[repr(C)]
struct PluginVtableUpTo13 {
    header: Header,
    name: unsafe extern "C" fn(obj: *mut c_void) -> StrView,
    init: unsafe extern "C" fn(
        obj: *mut c_void,
        args: *const PluginInitArgs,
        err: ErrorSink,
    ) -> Status,
    start: unsafe extern "C" fn(obj: *mut c_void, err: ErrorSink) -> Status,
    shutdown: unsafe extern "C" fn(obj: *mut c_void),
    destroy: unsafe extern "C" fn(obj: *mut c_void),
}

static VTABLE_1_3: PluginVtableUpTo13 = PluginVtableUpTo13 {
    header: Header {
        size: PluginVtable::SIZE_1_3 as u32,
        abi_minor: 3,
    },
    name: PluginObj::name,
    init: PluginObj::init,
    start: PluginObj::start,
    shutdown: PluginObj::shutdown,
    destroy: PluginObj::destroy,
};

struct PluginObj {
    plugin: Box<dyn Plugin>,
    name: String,
}

impl PluginObj {
    const VTABLE: PluginVtable = PluginVtable {
        header: Header::of::<PluginVtable>(),
        name: Self::name,
        init: Self::init,
        start: Self::start,
        shutdown: Self::shutdown,
        destroy: Self::destroy,
        post_start: Some(Self::post_start),
    };

    /// # Safety
    /// `obj` comes from `RawPlugin::new` and was not destroyed; no other reference is live.
    unsafe fn get<'a>(obj: *mut c_void) -> &'a mut PluginObj {
        // SAFETY: per the contract.
        unsafe { &mut *obj.cast::<PluginObj>() }
    }

    unsafe extern "C" fn name(obj: *mut c_void) -> StrView {
        // SAFETY: live plugin (vtable contract).
        StrView::new(&unsafe { Self::get(obj) }.name)
    }

    unsafe extern "C" fn init(
        obj: *mut c_void,
        args: *const PluginInitArgs,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live plugin; the host calls it from one thread.
        let this = unsafe { Self::get(obj) };
        // SAFETY: args valid for this call.
        let a = unsafe { &*args };
        // SAFETY: views valid for this call.
        let (json, location) = unsafe {
            (
                a.options_json.to_string_lossy(),
                a.location.to_string_lossy(),
            )
        };
        let options = PluginOptions::new(format!("plugin '{}'", this.name), json, location);
        let mut registrar = Registrar::from_raw(a.registrar);
        report(
            contain(|| this.plugin.initialize(&mut registrar, &options)),
            "initialize",
            err,
        )
    }

    unsafe extern "C" fn start(obj: *mut c_void, err: ErrorSink) -> Status {
        // SAFETY: live plugin.
        let this = unsafe { Self::get(obj) };
        report(contain(|| this.plugin.start()), "start", err)
    }

    unsafe extern "C" fn shutdown(obj: *mut c_void) {
        // SAFETY: live plugin.
        let this = unsafe { Self::get(obj) };
        if let Err(panic) = contain(|| this.plugin.shutdown()) {
            tracing::error!(target: "aimrt", "plugin '{}' panicked in shutdown: {panic}", this.name);
        }
    }

    unsafe extern "C" fn post_start(obj: *mut c_void) {
        // SAFETY: live plugin.
        let this = unsafe { Self::get(obj) };
        if let Err(panic) = contain(|| this.plugin.post_start()) {
            tracing::error!(target: "aimrt", "plugin '{}' panicked in post_start: {panic}", this.name);
        }
    }

    unsafe extern "C" fn destroy(obj: *mut c_void) {
        // SAFETY: called once, last; pointer from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast::<PluginObj>()) };
        let _ = contain(move || drop(b));
    }
}

pub(crate) fn report(
    r: Result<Result<(), crate::Error>, String>,
    hook: &str,
    err: ErrorSink,
) -> Status {
    match r {
        Ok(Ok(())) => Status::OK,
        Ok(Err(e)) => {
            err.report(&e.to_string());
            Status::FAILED
        }
        Err(panic) => {
            err.report(&format!("panicked in {hook}: {panic}"));
            Status::FAILED
        }
    }
}

impl RawPlugin {
    /// Exports a plugin (used by `export_plugin!` and by static registration).
    pub fn new(plugin: Box<dyn Plugin>) -> RawPlugin {
        let name = plugin.name().to_owned();
        RawPlugin {
            vtable: &PluginObj::VTABLE,
            obj: Box::into_raw(Box::new(PluginObj { plugin, name })).cast(),
        }
    }

    /// The same plugin behind a table in the 1.3 layout (no `post_start`), as a library
    /// built against 1.3 hands it over: for the fixture that proves such plugins load.
    #[doc(hidden)]
    pub fn as_1_3(self) -> RawPlugin {
        // The object moves to the new handle; this one must not destroy it.
        let this = std::mem::ManuallyDrop::new(self);
        RawPlugin {
            vtable: (&VTABLE_1_3 as *const PluginVtableUpTo13).cast(),
            obj: this.obj,
        }
    }

    fn vt(&self) -> &PluginVtableUpTo13 {
        // SAFETY: plugin tables are `'static` (their library is never unloaded), and every
        // minor's table starts with the 1.3 layout (append-only).
        unsafe { &*self.vtable.cast::<PluginVtableUpTo13>() }
    }

    /// Calls `post_start` if the plugin's table has it (1.4; host use).
    pub fn post_start(&mut self) {
        // SAFETY: every table starts with its header.
        let header = unsafe { &*self.vtable.cast::<Header>() };
        if (header.size as usize) < size_of::<PluginVtable>() {
            return;
        }
        // SAFETY: `size` covers the entry, so the table is a full 1.4 one.
        if let Some(f) = unsafe { (*self.vtable).post_start } {
            // SAFETY: live plugin.
            unsafe { f(self.obj) }
        }
    }

    /// The plugin's name (host use).
    pub fn name(&self) -> String {
        // SAFETY: live plugin; copied at once.
        unsafe { (self.vt().name)(self.obj).to_string_lossy() }
    }

    /// Calls `init` (host use).
    pub fn init(
        &mut self,
        host: &mut dyn RegistrarHost,
        options_json: &str,
        location: &str,
    ) -> Result<(), String> {
        RawRegistrar::with(host, |registrar| {
            let args = PluginInitArgs {
                header: Header::of::<PluginInitArgs>(),
                registrar,
                options_json: StrView::new(options_json),
                location: StrView::new(location),
            };
            let mut slot = ErrorSlot::default();
            // SAFETY: live plugin; args and the sink outlive the call.
            let status = unsafe { (self.vt().init)(self.obj, &args, slot.sink()) };
            slot.result(status)
        })
    }

    /// Calls `start` (host use).
    pub fn start(&mut self) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live plugin; the sink outlives the call.
        let status = unsafe { (self.vt().start)(self.obj, slot.sink()) };
        slot.result(status)
    }

    /// Calls `shutdown` (host use).
    pub fn shutdown(&mut self) {
        // SAFETY: live plugin.
        unsafe { (self.vt().shutdown)(self.obj) }
    }
}

impl Drop for RawPlugin {
    fn drop(&mut self) {
        // SAFETY: we own the plugin; this is its last use.
        unsafe { (self.vt().destroy)(self.obj) }
    }
}
