//! The core handle (host → module): one per module, valid for the process's life.

use std::ffi::c_void;
use std::sync::Arc;

use super::channel::TypeSupportVtable;
use super::executor::RawExecutor;
use super::logger::RawLogger;
use super::module::RawModuleInfo;
use super::pubsub::{MetaPair, MetaView, RawSubscriber, RawTopicStats};
use super::rpc_call::{RawRpcCtx, RawRpcReply, RawServiceFunc, RpcHandleVtable, INVOKE_BLOCKING};
use super::{contain, ErrorSink, ErrorSlot, Header, RawMessage, Status, StrView};
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

/// The channel handle of a module (ABI 1.1). Its object is the module's core object.
#[repr(C)]
pub struct ChannelHandleVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Registers `ts` as a type the module publishes on `topic` (only in `initialize`).
    pub register_publish_type: unsafe extern "C" fn(
        obj: *const c_void,
        topic: StrView,
        ts: *const TypeSupportVtable,
        err: ErrorSink,
    ) -> Status,
    /// Subscribes `sub` to messages of `ts` on `topic` (only in `initialize`); the host
    /// takes ownership of `sub`, also on failure.
    pub subscribe: unsafe extern "C" fn(
        obj: *const c_void,
        topic: StrView,
        ts: *const TypeSupportVtable,
        sub: RawSubscriber,
        err: ErrorSink,
    ) -> Status,
    /// Publishes `msg`, one reference to an object of `ts` that the host takes over (also
    /// on failure), with the context `ctx` (only from `start` until shutdown).
    pub publish: unsafe extern "C" fn(
        obj: *const c_void,
        topic: StrView,
        ctx: MetaView,
        ts: *const TypeSupportVtable,
        msg: *const c_void,
        err: ErrorSink,
    ) -> Status,
    /// The counters of `topic`; `NOT_FOUND` if no module registered or subscribed it.
    pub topic_stats:
        unsafe extern "C" fn(obj: *const c_void, topic: StrView, out: *mut RawTopicStats) -> Status,
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
    /// The module's channel handle (whose object is this core's object).
    pub channel:
        unsafe extern "C" fn(obj: *const c_void, out: *mut *const ChannelHandleVtable) -> Status,
    /// The module's RPC handle (ABI 1.2; whose object is this core's object).
    pub rpc: unsafe extern "C" fn(obj: *const c_void, out: *mut *const RpcHandleVtable) -> Status,
    /// The module's parameters (ABI 1.6; whose object is this core's object).
    pub parameter:
        unsafe extern "C" fn(obj: *const c_void, out: *mut *const ParameterHandleVtable) -> Status,
}

/// Reads the core table's entry that hands out a table `T` (after its size is checked).
type SubTableEntry<T> =
    fn(&CoreVtable) -> unsafe extern "C" fn(*const c_void, *mut *const T) -> Status;

/// Text handed to a callback for the duration of the call.
pub type TextCallback = unsafe extern "C" fn(ctx: *mut c_void, text: StrView);

/// Collects the texts a [`TextCallback`] is handed into the `Vec<String>` at `ctx`.
pub(crate) unsafe extern "C" fn collect_text(ctx: *mut c_void, text: StrView) {
    // SAFETY: `ctx` is the caller's `Vec<String>`, alive for the call (the `parameter_*`
    // methods of `RawCore`); the view is valid for this call.
    unsafe { (*ctx.cast::<Vec<String>>()).push(text.to_string_lossy()) };
}

/// A module's parameters (ABI 1.6): AimRT's per-module store of text values by text key.
/// Its object is the module's core object.
#[repr(C)]
pub struct ParameterHandleVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Calls `each` once with the value of `key` and returns `OK`, or returns `NOT_FOUND`.
    pub get: unsafe extern "C" fn(
        obj: *const c_void,
        key: StrView,
        ctx: *mut c_void,
        each: TextCallback,
    ) -> Status,
    /// Sets `key` to `value` (an empty value is a value).
    pub set: unsafe extern "C" fn(obj: *const c_void, key: StrView, value: StrView),
    /// Removes `key`: `OK`, or `NOT_FOUND` when it was not set.
    pub remove: unsafe extern "C" fn(obj: *const c_void, key: StrView) -> Status,
    /// Calls `each` with every key, in byte order.
    pub keys: unsafe extern "C" fn(obj: *const c_void, ctx: *mut c_void, each: TextCallback),
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
        rpc: Self::rpc,
        parameter: Self::parameter,
    };

    const PARAMETER: ParameterHandleVtable = ParameterHandleVtable {
        header: Header::of::<ParameterHandleVtable>(),
        get: Self::parameter_get,
        set: Self::parameter_set,
        remove: Self::parameter_remove,
        keys: Self::parameter_keys,
    };

    unsafe extern "C" fn parameter(
        _: *const c_void,
        out: *mut *const ParameterHandleVtable,
    ) -> Status {
        // SAFETY: `out` is writable (vtable contract).
        unsafe { out.write(&Self::PARAMETER) };
        Status::OK
    }

    unsafe extern "C" fn parameter_get(
        obj: *const c_void,
        key: StrView,
        ctx: *mut c_void,
        each: TextCallback,
    ) -> Status {
        // SAFETY: live core; the view is valid for this call.
        let (c, key) = unsafe { (Self::get(obj), key.to_string_lossy()) };
        match contain(|| c.parameter_get(&key)) {
            Ok(Some(value)) => {
                // SAFETY: the callee's contract: `each` with its `ctx`, the view valid for
                // the call.
                unsafe { each(ctx, StrView::new(&value)) };
                Status::OK
            }
            Ok(None) => Status::NOT_FOUND,
            Err(_) => Status::FAILED,
        }
    }

    unsafe extern "C" fn parameter_set(obj: *const c_void, key: StrView, value: StrView) {
        // SAFETY: live core; the views are valid for this call.
        let (c, key, value) = unsafe {
            (
                Self::get(obj),
                key.to_string_lossy(),
                value.to_string_lossy(),
            )
        };
        let _ = contain(|| c.parameter_set(&key, &value));
    }

    unsafe extern "C" fn parameter_remove(obj: *const c_void, key: StrView) -> Status {
        // SAFETY: live core; the view is valid for this call.
        let (c, key) = unsafe { (Self::get(obj), key.to_string_lossy()) };
        match contain(|| c.parameter_remove(&key)) {
            Ok(true) => Status::OK,
            Ok(false) => Status::NOT_FOUND,
            Err(_) => Status::FAILED,
        }
    }

    unsafe extern "C" fn parameter_keys(obj: *const c_void, ctx: *mut c_void, each: TextCallback) {
        // SAFETY: live core.
        let c = unsafe { Self::get(obj) };
        if let Ok(keys) = contain(|| c.parameter_keys()) {
            for k in &keys {
                // SAFETY: as in `parameter_get`.
                unsafe { each(ctx, StrView::new(k)) };
            }
        }
    }

    const RPC: RpcHandleVtable = RpcHandleVtable {
        header: Header::of::<RpcHandleVtable>(),
        register_service: Self::register_service,
        register_client: Self::register_client,
        invoke: Self::invoke,
        passed_keys: Self::passed_keys,
    };

    unsafe extern "C" fn passed_keys(
        obj: *const c_void,
        ctx: *mut c_void,
        each: unsafe extern "C" fn(ctx: *mut c_void, key: StrView),
    ) {
        // SAFETY: live core.
        let c = unsafe { Self::get(obj) };
        if let Ok(keys) = contain(|| c.passed_keys()) {
            for k in &keys {
                // SAFETY: the callee's contract: `each` with its `ctx`, the view valid for
                // the call.
                unsafe { each(ctx, StrView::new(k)) };
            }
        }
    }

    const CHANNEL: ChannelHandleVtable = ChannelHandleVtable {
        header: Header::of::<ChannelHandleVtable>(),
        register_publish_type: Self::register_publish_type,
        subscribe: Self::subscribe,
        publish: Self::publish,
        topic_stats: Self::topic_stats,
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

    unsafe extern "C" fn channel(_: *const c_void, out: *mut *const ChannelHandleVtable) -> Status {
        // SAFETY: `out` is writable (vtable contract).
        unsafe { out.write(&Self::CHANNEL) };
        Status::OK
    }

    unsafe extern "C" fn rpc(_: *const c_void, out: *mut *const RpcHandleVtable) -> Status {
        // SAFETY: `out` is writable (vtable contract).
        unsafe { out.write(&Self::RPC) };
        Status::OK
    }

    unsafe extern "C" fn register_service(
        obj: *const c_void,
        func: StrView,
        req_ts: *const TypeSupportVtable,
        rsp_ts: *const TypeSupportVtable,
        func_obj: RawServiceFunc,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live core; the view is valid for this call; tables are static data of
        // never-unloaded libraries.
        let (c, func, req_ts, rsp_ts) =
            unsafe { (Self::get(obj), func.to_string_lossy(), &*req_ts, &*rsp_ts) };
        super::invalid_unless_ok(
            contain(|| c.register_service(&func, req_ts, rsp_ts, func_obj)),
            err,
        )
    }

    unsafe extern "C" fn register_client(
        obj: *const c_void,
        func: StrView,
        req_ts: *const TypeSupportVtable,
        rsp_ts: *const TypeSupportVtable,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: as in `register_service`.
        let (c, func, req_ts, rsp_ts) =
            unsafe { (Self::get(obj), func.to_string_lossy(), &*req_ts, &*rsp_ts) };
        super::invalid_unless_ok(contain(|| c.register_client(&func, req_ts, rsp_ts)), err)
    }

    #[allow(clippy::too_many_arguments)] // the shape of the ABI entry
    unsafe extern "C" fn invoke(
        obj: *const c_void,
        func: StrView,
        ctx: RawRpcCtx,
        req_ts: *const TypeSupportVtable,
        req: *const c_void,
        rsp_ts: *const TypeSupportVtable,
        flags: u32,
        reply: RawRpcReply,
    ) {
        // SAFETY: live core; `req` is one reference to an object of the static table
        // `req_ts`, which we take over; the views are valid for this call.
        let (c, func, meta, req, rsp_ts) = unsafe {
            (
                Self::get(obj),
                func.as_str().unwrap_or(""),
                ctx.meta.pairs(),
                RawMessage::from_raw(&*req_ts, req),
                &*rsp_ts,
            )
        };
        let blocking = flags & INVOKE_BLOCKING != 0;
        // The host completes the reply exactly once, also when it panics: `invoke` owns it.
        let _ = contain(|| c.invoke(func, meta, ctx.timeout_ns, req, rsp_ts, blocking, reply));
    }

    unsafe extern "C" fn register_publish_type(
        obj: *const c_void,
        topic: StrView,
        ts: *const TypeSupportVtable,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live core; the view is valid for this call; tables are static data of
        // never-unloaded libraries.
        let (c, topic, ts) = unsafe { (Self::get(obj), topic.to_string_lossy(), &*ts) };
        super::invalid_unless_ok(contain(|| c.register_publish_type(&topic, ts)), err)
    }

    unsafe extern "C" fn subscribe(
        obj: *const c_void,
        topic: StrView,
        ts: *const TypeSupportVtable,
        sub: RawSubscriber,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: as in `register_publish_type`.
        let (c, topic, ts) = unsafe { (Self::get(obj), topic.to_string_lossy(), &*ts) };
        super::invalid_unless_ok(contain(|| c.subscribe(&topic, ts, sub)), err)
    }

    unsafe extern "C" fn publish(
        obj: *const c_void,
        topic: StrView,
        ctx: MetaView,
        ts: *const TypeSupportVtable,
        msg: *const c_void,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live core; `msg` is one reference to an object of the static table
        // `ts`, which we take over; the views are valid for this call.
        let (c, msg, topic, ctx) = unsafe {
            (
                Self::get(obj),
                RawMessage::from_raw(&*ts, msg),
                topic.as_bytes(),
                ctx.pairs(),
            )
        };
        super::invalid_unless_ok(contain(|| c.publish(topic, ctx, msg)), err)
    }

    unsafe extern "C" fn topic_stats(
        obj: *const c_void,
        topic: StrView,
        out: *mut RawTopicStats,
    ) -> Status {
        // SAFETY: live core; the view is valid for this call.
        let (c, topic) = unsafe { (Self::get(obj), topic.to_string_lossy()) };
        match contain(|| c.topic_stats(&topic)) {
            Ok(Some(stats)) => {
                // SAFETY: `out` is writable (vtable contract).
                unsafe { out.write(RawTopicStats::of(&stats)) };
                Status::OK
            }
            Ok(None) => Status::NOT_FOUND,
            Err(_) => Status::FAILED,
        }
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

    /// The table the core entry `entry` (ending at byte `end` of the core table) hands
    /// out: `None` when the core table is too short for the entry (which is then not
    /// read), the host refuses, or the table lacks an entry this crate uses. `header`
    /// reads the table's header.
    fn sub_table<T>(
        &self,
        end: usize,
        entry: SubTableEntry<T>,
        header: fn(&T) -> &Header,
    ) -> Option<&'static T> {
        let vt = self.vt();
        if !vt.header.has(end) {
            return None;
        }
        let get = entry(vt);
        let mut out: *const T = std::ptr::null();
        // SAFETY: live core whose table has the entry; `out` is writable.
        let status = unsafe { get(self.obj, &mut out) };
        if !status.is_ok() || out.is_null() {
            return None;
        }
        // SAFETY: the host's sub-tables are static data of the never-unloaded host.
        let table = unsafe { &*out };
        header(table).has(size_of::<T>()).then_some(table)
    }

    /// The channel handle, if the host has one with every entry this crate uses.
    pub(crate) fn channel(&self) -> Option<&'static ChannelHandleVtable> {
        let end = std::mem::offset_of!(CoreVtable, channel) + size_of::<usize>();
        self.sub_table(end, |c| c.channel, |t| &t.header)
    }

    /// The parameter handle, if the host has one (ABI 1.6).
    pub(crate) fn parameter(&self) -> Option<&'static ParameterHandleVtable> {
        let end = std::mem::offset_of!(CoreVtable, parameter) + size_of::<usize>();
        self.sub_table(end, |c| c.parameter, |t| &t.header)
    }

    /// The value of parameter `key` in `table` (this core's), if set.
    pub(crate) fn parameter_get(&self, table: &ParameterHandleVtable, key: &str) -> Option<String> {
        let mut out: Vec<String> = Vec::new();
        // SAFETY: live core of this table; the view and `out` outlive the call.
        let status = unsafe {
            (table.get)(
                self.obj,
                StrView::new(key),
                (&mut out as *mut Vec<String>).cast(),
                collect_text,
            )
        };
        status.is_ok().then(|| out.pop()).flatten()
    }

    /// Sets parameter `key` to `value` in `table` (this core's).
    pub(crate) fn parameter_set(&self, table: &ParameterHandleVtable, key: &str, value: &str) {
        // SAFETY: live core of this table; the views outlive the call.
        unsafe { (table.set)(self.obj, StrView::new(key), StrView::new(value)) }
    }

    /// Removes parameter `key` from `table` (this core's); whether it was set.
    pub(crate) fn parameter_remove(&self, table: &ParameterHandleVtable, key: &str) -> bool {
        // SAFETY: live core of this table; the view outlives the call.
        unsafe { (table.remove)(self.obj, StrView::new(key)) }.is_ok()
    }

    /// The parameter keys of `table` (this core's).
    pub(crate) fn parameter_keys(&self, table: &ParameterHandleVtable) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        // SAFETY: live core of this table; `out` outlives the call.
        unsafe {
            (table.keys)(
                self.obj,
                (&mut out as *mut Vec<String>).cast(),
                collect_text,
            )
        };
        out
    }

    /// The RPC handle, if the host has one with every entry this crate uses (ABI 1.2).
    pub(crate) fn rpc(&self) -> Option<&'static RpcHandleVtable> {
        let end = std::mem::offset_of!(CoreVtable, rpc) + size_of::<usize>();
        self.sub_table(end, |c| c.rpc, |t| &t.header)
    }

    pub(crate) fn register_service(
        &self,
        rpc: &RpcHandleVtable,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        rsp_ts: &'static TypeSupportVtable,
        func_obj: RawServiceFunc,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let func_obj = std::mem::ManuallyDrop::new(func_obj);
        // SAFETY: live core; ownership of `func_obj` passes to the host; the views and the
        // sink outlive the call.
        let status = unsafe {
            (rpc.register_service)(
                self.obj,
                StrView::new(func),
                req_ts,
                rsp_ts,
                std::ptr::read(&*func_obj),
                slot.sink(),
            )
        };
        slot.result(status)
    }

    pub(crate) fn register_client(
        &self,
        rpc: &RpcHandleVtable,
        func: &str,
        req_ts: &'static TypeSupportVtable,
        rsp_ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live core; the views and the sink outlive the call.
        let status = unsafe {
            (rpc.register_client)(self.obj, StrView::new(func), req_ts, rsp_ts, slot.sink())
        };
        slot.result(status)
    }

    /// The passed context keys plugins registered.
    pub(crate) fn passed_keys(&self, rpc: &RpcHandleVtable) -> Vec<String> {
        unsafe extern "C" fn each(ctx: *mut c_void, key: StrView) {
            // SAFETY: `ctx` is the `Vec<String>` below, alive for the call; the view is
            // valid for this call.
            unsafe { (*ctx.cast::<Vec<String>>()).push(key.to_string_lossy()) };
        }
        let mut keys: Vec<String> = Vec::new();
        // SAFETY: live core; `keys` outlives the call.
        unsafe { (rpc.passed_keys)(self.obj, (&mut keys as *mut Vec<String>).cast(), each) };
        keys
    }

    #[allow(clippy::too_many_arguments)] // one invoke entry, spelled out
    pub(crate) fn invoke(
        &self,
        rpc: &RpcHandleVtable,
        func: &str,
        meta: &[MetaPair<'_>],
        timeout_ns: u64,
        req: RawMessage,
        rsp_ts: &'static TypeSupportVtable,
        blocking: bool,
        reply: RawRpcReply,
    ) {
        let (req_ts, req) = req.into_raw();
        let flags = if blocking { INVOKE_BLOCKING } else { 0 };
        // SAFETY: live core; the request reference and the reply pass to the host; the
        // views outlive the call.
        unsafe {
            (rpc.invoke)(
                self.obj,
                StrView::new(func),
                RawRpcCtx::new(timeout_ns, meta),
                req_ts,
                req,
                rsp_ts,
                flags,
                reply,
            )
        }
    }

    pub(crate) fn register_publish_type(
        &self,
        ch: &ChannelHandleVtable,
        topic: &str,
        ts: &'static TypeSupportVtable,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live core; the views and the sink outlive the call.
        let status =
            unsafe { (ch.register_publish_type)(self.obj, StrView::new(topic), ts, slot.sink()) };
        slot.result(status)
    }

    pub(crate) fn subscribe(
        &self,
        ch: &ChannelHandleVtable,
        topic: &str,
        ts: &'static TypeSupportVtable,
        sub: RawSubscriber,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let sub = std::mem::ManuallyDrop::new(sub);
        // SAFETY: live core; ownership of `sub` passes to the host.
        let status = unsafe {
            (ch.subscribe)(
                self.obj,
                StrView::new(topic),
                ts,
                std::ptr::read(&*sub),
                slot.sink(),
            )
        };
        slot.result(status)
    }

    pub(crate) fn publish(
        &self,
        ch: &ChannelHandleVtable,
        topic: &str,
        ctx: &[MetaPair<'_>],
        msg: RawMessage,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let (ts, ptr) = msg.into_raw();
        // SAFETY: live core; the reference to `ptr` passes to the host; the views and the
        // sink outlive the call.
        let status = unsafe {
            (ch.publish)(
                self.obj,
                StrView::new(topic),
                MetaView::new(ctx),
                ts,
                ptr,
                slot.sink(),
            )
        };
        slot.result(status)
    }

    pub(crate) fn topic_stats(
        &self,
        ch: &ChannelHandleVtable,
        topic: &str,
    ) -> Option<crate::channel::TopicStats> {
        let mut out = RawTopicStats::zero();
        // SAFETY: live core; `out` is writable.
        let status = unsafe { (ch.topic_stats)(self.obj, StrView::new(topic), &mut out) };
        status.is_ok().then(|| out.to_stats())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    unsafe extern "C" fn info(_: *const c_void, _: *mut RawModuleInfo) {}
    unsafe extern "C" fn text(_: *const c_void) -> StrView {
        StrView::EMPTY
    }
    unsafe extern "C" fn get_executor(_: *const c_void, _: StrView, _: *mut RawExecutor) -> Status {
        Status::NOT_FOUND
    }
    unsafe extern "C" fn logger(_: *const c_void) -> RawLogger {
        unreachable!("not called here")
    }
    unsafe extern "C" fn channel(_: *const c_void, _: *mut *const ChannelHandleVtable) -> Status {
        Status::UNSUPPORTED
    }
    unsafe extern "C" fn rpc(_: *const c_void, _: *mut *const RpcHandleVtable) -> Status {
        Status::UNSUPPORTED
    }
    /// Past a 1.5 table's end: reading it would be reading another object's bytes.
    unsafe extern "C" fn parameter(
        _: *const c_void,
        _: *mut *const ParameterHandleVtable,
    ) -> Status {
        panic!("a core table of 1.5 has no `parameter`; its size says so")
    }

    /// A host of ABI 1.5 (its core table ends before `parameter`): no parameters, and
    /// the entry past the table's size is never called.
    #[test]
    fn a_core_table_of_1_5_has_no_parameters() {
        static TABLE_1_5: CoreVtable = CoreVtable {
            header: Header {
                size: std::mem::offset_of!(CoreVtable, parameter) as u32,
                abi_minor: 5,
            },
            info,
            config_file_path: text,
            config_json: text,
            get_executor,
            logger,
            channel,
            rpc,
            parameter,
        };
        let core = RawCore {
            vtable: &TABLE_1_5,
            obj: std::ptr::null(),
        };
        assert!(core.parameter().is_none());
        let err = crate::ParameterRef::new(core).unwrap_err().to_string();
        assert!(err.contains("came with ABI 1.6"), "{err}");
    }
}
