//! What a plugin can contribute (registrar, host → plugin) and the contributions'
//! vtables (plugin → host): executor types, services, RPC and channel backends, plus the
//! thread factory every executor thread goes through.

use std::ffi::c_void;
use std::marker::PhantomData;
use std::sync::Arc;

use super::channel_backend::RawChannelBackend;
use super::control::RawControl;
use super::executor::{ExecutorCreateArgs, RawExecutor};
use super::filter::RawChannelFilter;
use super::log_backend::RawLogBackendType;
use super::rpc::{RawHost, RawRpcBackend, RawService};
use super::rpc_filter::RawRpcFilter;
use super::{
    contain, invalid_unless_ok, ErrorSink, ErrorSlot, Header, RawCore, Status, StrView,
    TypeSupportVtable,
};
use crate::executor::ExecutorArgs;
use crate::thread::{ThreadConfigurator, ThreadSettingsRef};
use crate::{Error, Executor, ExecutorRef};

/// Thread settings as they cross the ABI.
#[repr(C)]
pub struct ThreadSettings {
    /// Size and minor of this struct.
    pub header: Header,
    /// Thread name (the factory shortens it to the OS limit as AimRT does).
    pub name: StrView,
    /// `""`, `SCHED_OTHER`, `SCHED_FIFO:<1-99>` or `SCHED_RR:<1-99>`.
    pub sched_policy: StrView,
    /// CPUs to bind to (empty: no binding).
    pub bind_cpu: *const u32,
    /// Length of `bind_cpu`.
    pub bind_cpu_len: usize,
}

/// The runtime's thread factory: applies name, policy and affinity to the calling thread.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawThreadFactory {
    /// The operations.
    pub vtable: *const ThreadFactoryVtable,
    /// The host's object.
    pub obj: *const c_void,
}

// SAFETY: the host's thread factory is thread-safe and never freed (exported by `leak`
// from a `Send + Sync` value).
unsafe impl Send for RawThreadFactory {}
// SAFETY: see `Send`.
unsafe impl Sync for RawThreadFactory {}

/// Thread factory operations.
#[repr(C)]
pub struct ThreadFactoryVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Applies `settings` to the calling thread; on a refused setting writes why to `err`
    /// and returns `INVALID` (the thread runs on with what could be applied).
    pub configure_current: unsafe extern "C" fn(
        obj: *const c_void,
        settings: *const ThreadSettings,
        err: ErrorSink,
    ) -> Status,
}

struct ExportThreads<T>(T);

impl<T: ThreadConfigurator> ExportThreads<T> {
    const VTABLE: ThreadFactoryVtable = ThreadFactoryVtable {
        header: Header::of::<ThreadFactoryVtable>(),
        configure_current: Self::configure_current,
    };

    unsafe extern "C" fn configure_current(
        obj: *const c_void,
        settings: *const ThreadSettings,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: `obj` is the leaked `Arc<T>` of `RawThreadFactory::leak::<T>`.
        let this = unsafe { &*obj.cast::<T>() };
        // SAFETY: the caller passes settings valid for this call.
        let s = unsafe { &*settings };
        // SAFETY: views and the CPU array are valid for this call.
        let (name, policy, cpus) = unsafe {
            (
                s.name.to_string_lossy(),
                s.sched_policy.to_string_lossy(),
                if s.bind_cpu_len == 0 || s.bind_cpu.is_null() {
                    Vec::new()
                } else {
                    std::slice::from_raw_parts(s.bind_cpu, s.bind_cpu_len).to_vec()
                },
            )
        };
        let settings = ThreadSettingsRef {
            name: &name,
            sched_policy: &policy,
            bind_cpu: &cpus,
            strict: false,
        };
        match contain(|| this.configure_current(&settings)) {
            Ok(Ok(())) => Status::OK,
            Ok(Err(why)) => {
                err.report(&why);
                Status::INVALID
            }
            Err(panic) => {
                err.report(&panic);
                Status::FAILED
            }
        }
    }
}

impl RawThreadFactory {
    /// Exports a thread configurator; leaked, as threads may use it until the process ends.
    pub fn leak<T: ThreadConfigurator>(t: Arc<T>) -> RawThreadFactory {
        RawThreadFactory {
            vtable: &ExportThreads::<T>::VTABLE,
            obj: Arc::into_raw(t).cast(),
        }
    }

    pub(crate) fn configure_current(&self, settings: &ThreadSettingsRef<'_>) -> Result<(), String> {
        let raw = ThreadSettings {
            header: Header::of::<ThreadSettings>(),
            name: StrView::new(settings.name),
            sched_policy: StrView::new(settings.sched_policy),
            bind_cpu: settings.bind_cpu.as_ptr(),
            bind_cpu_len: settings.bind_cpu.len(),
        };
        let mut slot = ErrorSlot::default();
        // SAFETY: a thread factory handle comes from `leak` (here or in the host) and is
        // valid forever; `raw` and the sink outlive the call.
        let status = unsafe { ((*self.vtable).configure_current)(self.obj, &raw, slot.sink()) };
        slot.result(status)
    }
}

/// An executor type contributed by a plugin.
#[repr(C)]
pub struct RawExecutorType {
    /// The operations.
    pub vtable: *const ExecutorTypeVtable,
    /// The plugin's object.
    pub obj: *const c_void,
}

// SAFETY: factories are `Send + Sync` (required by the exporter).
unsafe impl Send for RawExecutorType {}
// SAFETY: see `Send`.
unsafe impl Sync for RawExecutorType {}

/// Executor type operations.
#[repr(C)]
pub struct ExecutorTypeVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The type name the config uses (`type:`); valid until `drop`.
    pub type_name: unsafe extern "C" fn(obj: *const c_void) -> StrView,
    /// Number of option keys that name other executors.
    pub bind_key_count: unsafe extern "C" fn(obj: *const c_void) -> usize,
    /// The `index`-th bind key; valid until `drop`.
    pub bind_key: unsafe extern "C" fn(obj: *const c_void, index: usize) -> StrView,
    /// Builds an executor (not started); on failure writes why to `err`.
    pub create: unsafe extern "C" fn(
        obj: *const c_void,
        args: *const ExecutorCreateArgs,
        out: *mut RawExecutor,
        err: ErrorSink,
    ) -> Status,
    /// Frees the type.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
}

type Factory = dyn Fn(ExecutorArgs<'_>) -> Result<RawExecutor, Error> + Send + Sync;

struct ExecutorTypeObj {
    type_name: String,
    bind_keys: Vec<String>,
    factory: Box<Factory>,
}

impl ExecutorTypeObj {
    const VTABLE: ExecutorTypeVtable = ExecutorTypeVtable {
        header: Header::of::<ExecutorTypeVtable>(),
        type_name: Self::type_name,
        bind_key_count: Self::bind_key_count,
        bind_key: Self::bind_key,
        create: Self::create,
        drop: Self::drop,
    };

    /// # Safety
    /// `obj` comes from `RawExecutorType::new` and was not dropped.
    unsafe fn get<'a>(obj: *const c_void) -> &'a ExecutorTypeObj {
        // SAFETY: per the contract, a live `Box<ExecutorTypeObj>` pointer.
        unsafe { &*obj.cast::<ExecutorTypeObj>() }
    }

    unsafe extern "C" fn type_name(obj: *const c_void) -> StrView {
        // SAFETY: live object (vtable contract).
        StrView::new(&unsafe { Self::get(obj) }.type_name)
    }

    unsafe extern "C" fn bind_key_count(obj: *const c_void) -> usize {
        // SAFETY: live object.
        unsafe { Self::get(obj) }.bind_keys.len()
    }

    unsafe extern "C" fn bind_key(obj: *const c_void, index: usize) -> StrView {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        this.bind_keys
            .get(index)
            .map_or(StrView::EMPTY, |k| StrView::new(k))
    }

    unsafe extern "C" fn create(
        obj: *const c_void,
        args: *const ExecutorCreateArgs,
        out: *mut RawExecutor,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        // SAFETY: the host passes arguments valid for this call.
        let a = unsafe { &*args };
        // SAFETY: views and the bound array are valid for this call.
        let (name, options_json, location, bound) = unsafe {
            (
                a.name.to_string_lossy(),
                a.options_json.to_string_lossy(),
                a.location.to_string_lossy(),
                if a.bound_len == 0 || a.bound.is_null() {
                    Vec::new()
                } else {
                    std::slice::from_raw_parts(a.bound, a.bound_len)
                        .iter()
                        // The host passes live executors it built (or null).
                        .map(|raw| (!raw.is_null()).then(|| ExecutorRef::from_raw(*raw)))
                        .collect()
                },
            )
        };
        let args = ExecutorArgs {
            name: &name,
            options_json: &options_json,
            location: &location,
            bound,
            threads: crate::ThreadFactory::from_raw(a.threads),
        };
        let options_out = a
            .header
            .has(ExecutorCreateArgs::OPTIONS_OUT_END)
            .then_some(a.options_out);
        match super::with_options_out(options_out, || contain(|| (this.factory)(args))) {
            Ok(Ok(exec)) => {
                // SAFETY: `out` is writable (vtable contract).
                unsafe { out.write(exec) };
                Status::OK
            }
            Ok(Err(e)) => {
                err.report(&e.to_string());
                Status::INVALID
            }
            Err(panic) => {
                err.report(&format!("factory panicked: {panic}"));
                Status::FAILED
            }
        }
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: called once, last; the pointer came from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast_mut().cast::<ExecutorTypeObj>()) };
        let _ = contain(move || std::mem::drop(b));
    }
}

impl RawExecutorType {
    pub(crate) fn new<E, F>(type_name: &str, bind_keys: &[&str], factory: F) -> RawExecutorType
    where
        E: Executor,
        F: Fn(ExecutorArgs<'_>) -> Result<Arc<E>, Error> + Send + Sync + 'static,
    {
        let obj = Box::new(ExecutorTypeObj {
            type_name: type_name.to_owned(),
            bind_keys: bind_keys.iter().map(|k| (*k).to_owned()).collect(),
            factory: Box::new(move |args| factory(args).map(RawExecutor::new)),
        });
        RawExecutorType {
            vtable: &ExecutorTypeObj::VTABLE,
            obj: Box::into_raw(obj).cast_const().cast(),
        }
    }

    fn vt(&self) -> &ExecutorTypeVtable {
        // SAFETY: the vtable is `'static` (its library is never unloaded).
        unsafe { &*self.vtable }
    }

    /// The type name (host use).
    pub fn type_name(&self) -> String {
        // SAFETY: live object; view copied at once.
        unsafe { (self.vt().type_name)(self.obj).to_string_lossy() }
    }

    /// The option keys that name other executors (host use).
    pub fn bind_keys(&self) -> Vec<String> {
        // SAFETY: live object; views copied at once.
        let n = unsafe { (self.vt().bind_key_count)(self.obj) };
        (0..n)
            // SAFETY: as above, index in range.
            .map(|i| unsafe { (self.vt().bind_key)(self.obj, i).to_string_lossy() })
            .collect()
    }

    /// Builds an executor (host use).
    pub fn create(
        &self,
        name: &str,
        options_json: &str,
        location: &str,
        bound: &[RawExecutor],
        threads: RawThreadFactory,
    ) -> Result<(RawExecutor, Option<String>), String> {
        let mut reported = ErrorSlot::default();
        let args = ExecutorCreateArgs {
            header: Header::of::<ExecutorCreateArgs>(),
            name: StrView::new(name),
            options_json: StrView::new(options_json),
            location: StrView::new(location),
            bound: bound.as_ptr(),
            bound_len: bound.len(),
            threads,
            options_out: reported.sink(),
        };
        let mut out = RawExecutor::null();
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; args, out and the sinks outlive the call.
        let status = unsafe { (self.vt().create)(self.obj, &args, &mut out, slot.sink()) };
        if status.is_ok() && !out.is_null() {
            Ok((out, reported.taken()))
        } else {
            Err(slot.take(|| format!("factory returned {status}")))
        }
    }
}

impl Drop for RawExecutorType {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { (self.vt().drop)(self.obj) }
    }
}

/// The registrar a plugin gets in `init`: valid only during that call.
#[repr(C)]
#[derive(Clone, Copy)]
pub struct RawRegistrar {
    /// The operations.
    pub vtable: *const RegistrarVtable,
    /// The host's object.
    pub obj: *mut c_void,
}

/// Registrar operations.
#[repr(C)]
pub struct RegistrarVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Registers an executor type; the host takes ownership of `ty` (also on failure).
    pub register_executor_type:
        unsafe extern "C" fn(obj: *mut c_void, ty: RawExecutorType, err: ErrorSink) -> Status,
    /// The runtime's thread factory.
    pub thread_factory: unsafe extern "C" fn(obj: *mut c_void) -> RawThreadFactory,
    /// Registers a service method under `func_name`; the host takes ownership.
    pub register_service: unsafe extern "C" fn(
        obj: *mut c_void,
        func_name: StrView,
        service: RawService,
        err: ErrorSink,
    ) -> Status,
    /// Registers an RPC backend; the host takes ownership.
    pub register_rpc_backend:
        unsafe extern "C" fn(obj: *mut c_void, backend: RawRpcBackend, err: ErrorSink) -> Status,
    /// Registers a channel backend; the host takes ownership.
    pub register_channel_backend: unsafe extern "C" fn(
        obj: *mut c_void,
        backend: RawChannelBackend,
        err: ErrorSink,
    ) -> Status,
    /// The host handle backends use to invoke services.
    pub host: unsafe extern "C" fn(obj: *mut c_void) -> RawHost,
    /// (1.2) Adds a context meta key that a module's client context made from a server
    /// context takes over (AimRT's `AddPassedContextMetaKeys`, e.g. a trace id).
    pub add_passed_context_meta_key:
        unsafe extern "C" fn(obj: *mut c_void, key: StrView, err: ErrorSink) -> Status,
    /// (1.3) Loads the type support package at `path` (a library made with
    /// `export_type_support!`) and hands each of its type names to `each(ctx, name)`.
    pub load_type_support_pkg: unsafe extern "C" fn(
        obj: *mut c_void,
        path: StrView,
        ctx: *mut c_void,
        each: unsafe extern "C" fn(ctx: *mut c_void, name: StrView),
        err: ErrorSink,
    ) -> Status,
    /// (1.3) The table of a message type loaded from a type support package, or null.
    pub find_type_support:
        unsafe extern "C" fn(obj: *mut c_void, name: StrView) -> *const TypeSupportVtable,
    /// (1.3) The plugin's core: its channel handle subscribes and registers publish types
    /// during `init` (applied once the channel is configured, before modules initialize)
    /// and publishes from `start` on. Valid for the process's life.
    pub core: unsafe extern "C" fn(obj: *mut c_void) -> RawCore,
    /// (1.7) Registers a channel filter under `name` for `side` (0 publish, 1 subscribe:
    /// [`FilterSide::code`](crate::channel::FilterSide::code)); the host takes ownership
    /// of `filter` (also on failure).
    pub register_channel_filter: unsafe extern "C" fn(
        obj: *mut c_void,
        name: StrView,
        side: u32,
        filter: RawChannelFilter,
        err: ErrorSink,
    ) -> Status,
    /// (1.7) Replaces the plugin's `options` in the normalized config (`--dump_cfg_file`)
    /// with `json`, the options as the plugin reads them, defaults filled in (AimRT's
    /// `UpdatePluginOptionsNode`).
    pub update_options:
        unsafe extern "C" fn(obj: *mut c_void, json: StrView, err: ErrorSink) -> Status,
    /// (1.9) Registers an RPC filter under `name` for `side` (0 client, 1 server:
    /// [`CallFilterSide::code`](crate::rpc::CallFilterSide::code)); the host takes
    /// ownership of `filter` (also on failure).
    pub register_rpc_filter: unsafe extern "C" fn(
        obj: *mut c_void,
        name: StrView,
        side: u32,
        filter: RawRpcFilter,
        err: ErrorSink,
    ) -> Status,
    /// (1.10) Registers a log backend type (named by its `type_name`); the host takes
    /// ownership of `ty` (also on failure).
    pub register_log_backend_type:
        unsafe extern "C" fn(obj: *mut c_void, ty: RawLogBackendType, err: ErrorSink) -> Status,
    /// (1.13) The runtime's control handle (loggers' levels, modules' parameters), valid
    /// for the process's life.
    pub control: unsafe extern "C" fn(obj: *mut c_void) -> RawControl,
}

/// The size of a registrar table of ABI 1.2 (up to `add_passed_context_meta_key`).
const REGISTRAR_SIZE_1_2: usize = std::mem::offset_of!(RegistrarVtable, load_type_support_pkg);
/// The size of a registrar table of ABI 1.3 to 1.6 (up to `core`).
const REGISTRAR_SIZE_1_3: usize = std::mem::offset_of!(RegistrarVtable, register_channel_filter);
/// The size of a registrar table of ABI 1.7 and 1.8 (up to `update_options`).
const REGISTRAR_SIZE_1_7: usize = std::mem::offset_of!(RegistrarVtable, register_rpc_filter);
/// The size of a registrar table of ABI 1.9 (up to `register_rpc_filter`).
const REGISTRAR_SIZE_1_9: usize = std::mem::offset_of!(RegistrarVtable, register_log_backend_type);
/// The size of a registrar table of ABI 1.10 to 1.12 (up to `register_log_backend_type`).
const REGISTRAR_SIZE_1_10: usize = std::mem::offset_of!(RegistrarVtable, control);

/// What the runtime implements behind the registrar.
pub trait RegistrarHost {
    /// Records an executor type.
    fn register_executor_type(&mut self, ty: RawExecutorType) -> Result<(), String>;
    /// The thread factory for executor threads.
    fn thread_factory(&self) -> RawThreadFactory;
    /// Records a service under its full function name.
    fn register_service(&mut self, func_name: &str, service: RawService) -> Result<(), String>;
    /// Records an RPC backend.
    fn register_rpc_backend(&mut self, backend: RawRpcBackend) -> Result<(), String>;
    /// Records a channel backend.
    fn register_channel_backend(&mut self, backend: RawChannelBackend) -> Result<(), String>;
    /// The host handle through which backends invoke services.
    fn host(&self) -> RawHost;
    /// Records a context meta key passed from server contexts to client contexts.
    fn add_passed_context_meta_key(&mut self, key: &str) -> Result<(), String>;
    /// Loads a type support package; the names of its types.
    fn load_type_support_pkg(&mut self, path: &str) -> Result<Vec<String>, String>;
    /// A message type loaded from a type support package.
    fn find_type_support(&self, name: &str) -> Option<&'static TypeSupportVtable>;
    /// The plugin's core (one per plugin, made on first use).
    fn core(&mut self) -> RawCore;
    /// Records a channel filter of `side` under `name`.
    fn register_channel_filter(
        &mut self,
        name: &str,
        side: crate::channel::FilterSide,
        filter: RawChannelFilter,
    ) -> Result<(), String>;
    /// Records the plugin's options as it reads them (JSON), for the normalized config.
    fn update_options(&mut self, json: &str) -> Result<(), String>;
    /// Records an RPC filter of `side` under `name`.
    fn register_rpc_filter(
        &mut self,
        name: &str,
        side: crate::rpc::CallFilterSide,
        filter: RawRpcFilter,
    ) -> Result<(), String>;
    /// Records a log backend type.
    fn register_log_backend_type(&mut self, ty: RawLogBackendType) -> Result<(), String>;
    /// The runtime's control handle.
    fn control(&self) -> RawControl;
}

struct ExportRegistrar<'a>(PhantomData<&'a ()>);

impl ExportRegistrar<'_> {
    const VTABLE: RegistrarVtable = RegistrarVtable {
        header: Header::of::<RegistrarVtable>(),
        register_executor_type: Self::register_executor_type,
        thread_factory: Self::thread_factory,
        register_service: Self::register_service,
        register_rpc_backend: Self::register_rpc_backend,
        register_channel_backend: Self::register_channel_backend,
        host: Self::host,
        add_passed_context_meta_key: Self::add_passed_context_meta_key,
        load_type_support_pkg: Self::load_type_support_pkg,
        find_type_support: Self::find_type_support,
        core: Self::core,
        register_channel_filter: Self::register_channel_filter,
        update_options: Self::update_options,
        register_rpc_filter: Self::register_rpc_filter,
        register_log_backend_type: Self::register_log_backend_type,
        control: Self::control,
    };

    unsafe extern "C" fn control(obj: *mut c_void) -> RawControl {
        // SAFETY: as in `register_executor_type`.
        let host = unsafe { Self::get(obj) };
        host.control()
    }

    unsafe extern "C" fn register_log_backend_type(
        obj: *mut c_void,
        ty: RawLogBackendType,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: as in `register_executor_type`.
        let host = unsafe { Self::get(obj) };
        invalid_unless_ok(contain(|| host.register_log_backend_type(ty)), err)
    }

    unsafe extern "C" fn register_rpc_filter(
        obj: *mut c_void,
        name: StrView,
        side: u32,
        filter: RawRpcFilter,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: as in `register_executor_type`; the view is valid for this call.
        let (host, name) = unsafe { (Self::get(obj), name.to_string_lossy()) };
        let Some(side) = crate::rpc::CallFilterSide::from_code(side) else {
            err.report(&format!(
                "rpc filter '{name}': side {side} is neither client (0) nor server (1)"
            ));
            return Status::INVALID;
        };
        invalid_unless_ok(
            contain(|| host.register_rpc_filter(&name, side, filter)),
            err,
        )
    }

    unsafe extern "C" fn update_options(obj: *mut c_void, json: StrView, err: ErrorSink) -> Status {
        // SAFETY: as in `register_executor_type`; the view is valid for this call.
        let (host, json) = unsafe { (Self::get(obj), json.to_string_lossy()) };
        invalid_unless_ok(contain(|| host.update_options(&json)), err)
    }

    unsafe extern "C" fn register_channel_filter(
        obj: *mut c_void,
        name: StrView,
        side: u32,
        filter: RawChannelFilter,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: as in `register_executor_type`; the view is valid for this call.
        let (host, name) = unsafe { (Self::get(obj), name.to_string_lossy()) };
        let Some(side) = crate::channel::FilterSide::from_code(side) else {
            err.report(&format!(
                "channel filter '{name}': side {side} is neither publish (0) nor subscribe (1)"
            ));
            return Status::INVALID;
        };
        invalid_unless_ok(
            contain(|| host.register_channel_filter(&name, side, filter)),
            err,
        )
    }

    unsafe extern "C" fn load_type_support_pkg(
        obj: *mut c_void,
        path: StrView,
        ctx: *mut c_void,
        each: unsafe extern "C" fn(ctx: *mut c_void, name: StrView),
        err: ErrorSink,
    ) -> Status {
        // SAFETY: as in `register_executor_type`; the view is valid for this call.
        let (host, path) = unsafe { (Self::get(obj), path.to_string_lossy()) };
        match contain(|| host.load_type_support_pkg(&path)) {
            Ok(Ok(names)) => {
                for n in &names {
                    // SAFETY: the caller's callback with its `ctx`; the view is valid for
                    // the call.
                    unsafe { each(ctx, StrView::new(n)) };
                }
                Status::OK
            }
            Ok(Err(why)) | Err(why) => {
                err.report(&why);
                Status::INVALID
            }
        }
    }

    unsafe extern "C" fn find_type_support(
        obj: *mut c_void,
        name: StrView,
    ) -> *const TypeSupportVtable {
        // SAFETY: as above.
        let (host, name) = unsafe { (Self::get(obj), name.to_string_lossy()) };
        match contain(|| host.find_type_support(&name)) {
            Ok(Some(ts)) => ts,
            _ => std::ptr::null(),
        }
    }

    unsafe extern "C" fn core(obj: *mut c_void) -> RawCore {
        // SAFETY: as above.
        let host = unsafe { Self::get(obj) };
        host.core()
    }

    unsafe extern "C" fn add_passed_context_meta_key(
        obj: *mut c_void,
        key: StrView,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: as in `register_executor_type`; the view is valid for this call.
        let (host, key) = unsafe { (Self::get(obj), key.to_string_lossy()) };
        invalid_unless_ok(contain(|| host.add_passed_context_meta_key(&key)), err)
    }

    /// # Safety
    /// `obj` is the `&mut &mut dyn RegistrarHost` of `RawRegistrar::with`, during its call.
    unsafe fn get<'b>(obj: *mut c_void) -> &'b mut dyn RegistrarHost {
        // SAFETY: per the contract.
        unsafe { &mut **obj.cast::<&mut dyn RegistrarHost>() }
    }

    unsafe extern "C" fn register_executor_type(
        obj: *mut c_void,
        ty: RawExecutorType,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: called by the plugin during `init` (registrar contract).
        let host = unsafe { Self::get(obj) };
        invalid_unless_ok(contain(|| host.register_executor_type(ty)), err)
    }

    unsafe extern "C" fn thread_factory(obj: *mut c_void) -> RawThreadFactory {
        // SAFETY: as above.
        let host = unsafe { Self::get(obj) };
        host.thread_factory()
    }

    unsafe extern "C" fn register_service(
        obj: *mut c_void,
        func: StrView,
        service: RawService,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: called by the plugin during `init` (registrar contract).
        let host = unsafe { Self::get(obj) };
        // SAFETY: the view is valid for this call.
        let func = unsafe { func.to_string_lossy() };
        invalid_unless_ok(contain(|| host.register_service(&func, service)), err)
    }

    unsafe extern "C" fn register_rpc_backend(
        obj: *mut c_void,
        backend: RawRpcBackend,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: called by the plugin during `init` (registrar contract).
        let host = unsafe { Self::get(obj) };
        invalid_unless_ok(contain(|| host.register_rpc_backend(backend)), err)
    }

    unsafe extern "C" fn register_channel_backend(
        obj: *mut c_void,
        backend: RawChannelBackend,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: called by the plugin during `init` (registrar contract).
        let host = unsafe { Self::get(obj) };
        invalid_unless_ok(contain(|| host.register_channel_backend(backend)), err)
    }

    unsafe extern "C" fn host(obj: *mut c_void) -> RawHost {
        // SAFETY: as above.
        let host = unsafe { Self::get(obj) };
        host.host()
    }
}

impl RawRegistrar {
    /// Exports `host` as a registrar for the duration of `f` (host use).
    pub fn with<R>(host: &mut dyn RegistrarHost, f: impl FnOnce(RawRegistrar) -> R) -> R {
        let mut host_ref: &mut dyn RegistrarHost = host;
        let raw = RawRegistrar {
            vtable: &ExportRegistrar::VTABLE,
            obj: (&mut host_ref as *mut &mut dyn RegistrarHost).cast(),
        };
        f(raw)
    }

    fn vt(&self) -> &RegistrarVtable {
        // SAFETY: registrars are only valid during `init`, where the host's vtable is live.
        unsafe { &*self.vtable }
    }

    pub(crate) fn register_executor_type(&self, ty: RawExecutorType) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let ty = std::mem::ManuallyDrop::new(ty);
        // SAFETY: during `init`; ownership of `ty` passes to the host (not dropped here).
        let status = unsafe {
            (self.vt().register_executor_type)(self.obj, std::ptr::read(&*ty), slot.sink())
        };
        slot.result(status)
    }

    pub(crate) fn thread_factory(&self) -> RawThreadFactory {
        // SAFETY: during `init`.
        unsafe { (self.vt().thread_factory)(self.obj) }
    }

    pub(crate) fn register_service(
        &self,
        func_name: &str,
        service: RawService,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let service = std::mem::ManuallyDrop::new(service);
        // SAFETY: during `init`; ownership of `service` passes to the host.
        let status = unsafe {
            (self.vt().register_service)(
                self.obj,
                StrView::new(func_name),
                std::ptr::read(&*service),
                slot.sink(),
            )
        };
        slot.result(status)
    }

    pub(crate) fn register_rpc_backend(&self, backend: RawRpcBackend) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let backend = std::mem::ManuallyDrop::new(backend);
        // SAFETY: during `init`; ownership of `backend` passes to the host.
        let status = unsafe {
            (self.vt().register_rpc_backend)(self.obj, std::ptr::read(&*backend), slot.sink())
        };
        slot.result(status)
    }

    pub(crate) fn add_passed_context_meta_key(&self, key: &str) -> Result<(), String> {
        if !self.vt().header.has(REGISTRAR_SIZE_1_2) {
            return Err("this aimrt_main predates passed context keys (ABI 1.2)".into());
        }
        let mut slot = ErrorSlot::default();
        // SAFETY: during `init`, with the entry; the view and the sink outlive the call.
        let status = unsafe {
            (self.vt().add_passed_context_meta_key)(self.obj, StrView::new(key), slot.sink())
        };
        slot.result(status)
    }

    pub(crate) fn register_channel_filter(
        &self,
        name: &str,
        side: crate::channel::FilterSide,
        filter: RawChannelFilter,
    ) -> Result<(), String> {
        if !self
            .vt()
            .header
            .has(REGISTRAR_SIZE_1_3 + size_of::<usize>())
        {
            return Err("this aimrt_main predates channel filters from plugins (ABI 1.7); run a newer aimrt_main".into());
        }
        self.register_filter(self.vt().register_channel_filter, name, side.code(), filter)
    }

    pub(crate) fn register_rpc_filter(
        &self,
        name: &str,
        side: crate::rpc::CallFilterSide,
        filter: RawRpcFilter,
    ) -> Result<(), String> {
        if !self.vt().header.has(REGISTRAR_SIZE_1_9) {
            return Err("this aimrt_main predates RPC filters from plugins (ABI 1.9); run a newer aimrt_main".into());
        }
        self.register_filter(self.vt().register_rpc_filter, name, side.code(), filter)
    }

    pub(crate) fn register_log_backend_type(&self, ty: RawLogBackendType) -> Result<(), String> {
        if !self.vt().header.has(REGISTRAR_SIZE_1_10) {
            return Err("this aimrt_main predates log backends from plugins (ABI 1.10); run a newer aimrt_main".into());
        }
        let mut slot = ErrorSlot::default();
        // SAFETY: during `init`, with the entry (size checked); `ty` moves to the host; the
        // sink outlives the call.
        let status = unsafe { (self.vt().register_log_backend_type)(self.obj, ty, slot.sink()) };
        slot.result(status)
    }

    pub(crate) fn control(&self) -> Result<RawControl, String> {
        if !self.vt().header.has(size_of::<RegistrarVtable>()) {
            return Err("this aimrt_main predates the control of loggers and parameters from plugins (ABI 1.13); run a newer aimrt_main".into());
        }
        // SAFETY: during `init`, with the entry (size checked).
        Ok(unsafe { (self.vt().control)(self.obj) })
    }

    /// Hands `filter` to `entry`, one of the registrar's filter entries, which the caller
    /// found within the table's size; ownership of `filter` passes to the host.
    fn register_filter<T>(
        &self,
        entry: unsafe extern "C" fn(*mut c_void, StrView, u32, T, ErrorSink) -> Status,
        name: &str,
        side: u32,
        filter: T,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: during `init`, with an entry the caller checked against the table's
        // size; `filter` moves to the host; the view and the sink outlive the call.
        let status = unsafe { entry(self.obj, StrView::new(name), side, filter, slot.sink()) };
        slot.result(status)
    }

    /// `Ok(false)`: the host predates the entry (ABI 1.7) and keeps the options as written.
    pub(crate) fn update_options(&self, json: &str) -> Result<bool, String> {
        if !self.vt().header.has(REGISTRAR_SIZE_1_7) {
            return Ok(false);
        }
        let mut slot = ErrorSlot::default();
        // SAFETY: during `init`, with the entry (size checked); the view and the sink
        // outlive the call.
        let status =
            unsafe { (self.vt().update_options)(self.obj, StrView::new(json), slot.sink()) };
        slot.result(status).map(|()| true)
    }

    fn has_1_3(&self) -> Result<(), String> {
        if self.vt().header.has(REGISTRAR_SIZE_1_3) {
            Ok(())
        } else {
            Err("this aimrt_main predates type support packages and plugin channels (ABI 1.3); run a newer aimrt_main".into())
        }
    }

    pub(crate) fn load_type_support_pkg(&self, path: &str) -> Result<Vec<String>, String> {
        self.has_1_3()?;
        unsafe extern "C" fn push(ctx: *mut c_void, name: StrView) {
            // SAFETY: `ctx` is the `Vec<String>` below, alive for the call; the view is
            // valid for this call.
            unsafe { (*ctx.cast::<Vec<String>>()).push(name.to_string_lossy()) };
        }
        let mut names: Vec<String> = Vec::new();
        let mut slot = ErrorSlot::default();
        // SAFETY: during `init`, with the entry; the views, `names` and the sink outlive
        // the call.
        let status = unsafe {
            (self.vt().load_type_support_pkg)(
                self.obj,
                StrView::new(path),
                (&mut names as *mut Vec<String>).cast(),
                push,
                slot.sink(),
            )
        };
        slot.result(status).map(|()| names)
    }

    pub(crate) fn find_type_support(&self, name: &str) -> Option<&'static TypeSupportVtable> {
        self.has_1_3().ok()?;
        // SAFETY: during `init`, with the entry; tables the host returns are static data of
        // never-unloaded libraries.
        unsafe { (self.vt().find_type_support)(self.obj, StrView::new(name)).as_ref() }
    }

    pub(crate) fn core(&self) -> Result<RawCore, String> {
        self.has_1_3()?;
        // SAFETY: during `init`, with the entry.
        Ok(unsafe { (self.vt().core)(self.obj) })
    }

    pub(crate) fn register_channel_backend(
        &self,
        backend: RawChannelBackend,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let backend = std::mem::ManuallyDrop::new(backend);
        // SAFETY: during `init`; ownership of `backend` passes to the host.
        let status = unsafe {
            (self.vt().register_channel_backend)(self.obj, std::ptr::read(&*backend), slot.sink())
        };
        slot.result(status)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::channel::{FilterSide, Next, Publication};

    #[derive(Debug, serde::Deserialize, serde::Serialize)]
    #[serde(deny_unknown_fields)]
    struct PoolOptions {
        #[serde(default = "two")]
        thread_num: u32,
        #[serde(default)]
        thread_sched_policy: String,
    }

    fn two() -> u32 {
        2
    }

    /// Creates an executor of a type whose factory reads [`PoolOptions`] with
    /// `read_options`, through arguments of `size` bytes; what the factory reported.
    fn reported_through(size: usize) -> Option<String> {
        let ty = RawExecutorType::new("pool", &[], |args: ExecutorArgs<'_>| {
            let o: PoolOptions = args.read_options()?;
            assert_eq!(
                (o.thread_num, o.thread_sched_policy.as_str()),
                (2, "FIFO:10")
            );
            Ok(Arc::new(crate::test_util::Inline))
        });
        let mut reported = ErrorSlot::default();
        let mut args = ExecutorCreateArgs {
            header: Header::of::<ExecutorCreateArgs>(),
            name: StrView::new("pool"),
            options_json: StrView::new(r#"{"thread_sched_policy": "FIFO:10"}"#),
            location: StrView::new("cfg.yaml:3:5"),
            bound: std::ptr::null(),
            bound_len: 0,
            threads: crate::ThreadFactory::plain().raw(),
            options_out: reported.sink(),
        };
        args.header.size = size as u32;
        let mut out = RawExecutor::null();
        let mut err = ErrorSlot::default();
        // SAFETY: live type; the arguments, `out` and the sinks outlive the call.
        let status = unsafe { (ty.vt().create)(ty.obj, &args, &mut out, err.sink()) };
        assert_eq!(err.result(status), Ok(()));
        assert!(!out.is_null());
        reported.taken()
    }

    #[test]
    fn an_executor_factory_reports_its_options_as_read_to_a_host_of_1_8_only() {
        assert_eq!(
            reported_through(size_of::<ExecutorCreateArgs>()).as_deref(),
            Some(r#"{"thread_num":2,"thread_sched_policy":"FIFO:10"}"#)
        );
        // A host of 1.7 passes arguments without `options_out`: the factory only reads.
        let size_1_7 = std::mem::offset_of!(ExecutorCreateArgs, options_out);
        assert_eq!(reported_through(size_1_7), None);
    }

    #[test]
    fn a_registrar_of_1_6_refuses_filters_and_keeps_what_it_has() {
        static TABLE_1_6: RegistrarVtable = RegistrarVtable {
            header: Header {
                size: REGISTRAR_SIZE_1_3 as u32,
                abi_minor: 6,
            },
            ..ExportRegistrar::VTABLE
        };
        // The host object is never reached: the size check answers first.
        let raw = RawRegistrar {
            vtable: &TABLE_1_6,
            obj: std::ptr::null_mut(),
        };
        assert!(raw.has_1_3().is_ok());
        let filter = RawChannelFilter::new(|_: &Publication<'_>, next: Next<'_>| next.pass());
        let err = raw
            .register_channel_filter("f", FilterSide::Publish, filter)
            .unwrap_err();
        assert!(err.contains("(ABI 1.7)"), "{err}");
        assert_eq!(raw.update_options("{}"), Ok(false));
        assert!(ExportRegistrar::VTABLE
            .header
            .has(size_of::<RegistrarVtable>()));
    }

    #[test]
    fn a_registrar_of_1_8_refuses_rpc_filters_and_still_takes_options() {
        static TABLE_1_8: RegistrarVtable = RegistrarVtable {
            header: Header {
                size: REGISTRAR_SIZE_1_7 as u32,
                abi_minor: 8,
            },
            ..ExportRegistrar::VTABLE
        };
        let raw = RawRegistrar {
            vtable: &TABLE_1_8,
            obj: std::ptr::null_mut(),
        };
        let filter = RawRpcFilter::new(
            |_: &crate::rpc::FilterCall<'_>, next: crate::rpc::CallNext<'_>| next.pass(),
        );
        let err = raw
            .register_rpc_filter("f", crate::rpc::CallFilterSide::Client, filter)
            .unwrap_err();
        assert!(err.contains("(ABI 1.9)"), "{err}");
        // `update_options` is within 1.8's table: it is called (and reaches the host).
        assert!(TABLE_1_8.header.has(REGISTRAR_SIZE_1_7));
        assert!(!TABLE_1_8.header.has(size_of::<RegistrarVtable>()));
    }

    #[test]
    fn a_registrar_of_1_9_refuses_log_backend_types() {
        static TABLE_1_9: RegistrarVtable = RegistrarVtable {
            header: Header {
                size: REGISTRAR_SIZE_1_9 as u32,
                abi_minor: 9,
            },
            ..ExportRegistrar::VTABLE
        };
        let raw = RawRegistrar {
            vtable: &TABLE_1_9,
            obj: std::ptr::null_mut(),
        };
        struct Nowhere;
        impl crate::LogBackend for Nowhere {
            fn write(&mut self, _: &crate::LogEntry<'_>) -> Result<(), String> {
                Ok(())
            }
        }
        let ty = RawLogBackendType::new("nowhere", |_: &crate::BackendOptions| Ok(Nowhere));
        let err = raw.register_log_backend_type(ty).unwrap_err();
        assert!(err.contains("(ABI 1.10)"), "{err}");
        // 1.9's own entry is within the table.
        assert!(TABLE_1_9.header.has(REGISTRAR_SIZE_1_9));
    }

    #[test]
    fn a_registrar_of_1_12_refuses_the_control_handle() {
        static TABLE_1_12: RegistrarVtable = RegistrarVtable {
            header: Header {
                size: REGISTRAR_SIZE_1_10 as u32,
                abi_minor: 12,
            },
            ..ExportRegistrar::VTABLE
        };
        let raw = RawRegistrar {
            vtable: &TABLE_1_12,
            obj: std::ptr::null_mut(),
        };
        let err = raw.control().map(|_| ()).unwrap_err();
        assert!(err.contains("(ABI 1.13)"), "{err}");
        // 1.10's entry is within the table.
        assert!(TABLE_1_12.header.has(REGISTRAR_SIZE_1_10));
    }
}
