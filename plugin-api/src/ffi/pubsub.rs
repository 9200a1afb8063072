//! Publish/subscribe across the ABI (DESIGN §6).
//!
//! - A module's **subscriber** ([`RawSubscriber`], module → host) is called with a context
//!   and one reference to a message object of the table it subscribed with.
//! - The host hands a backend one **sink** per subscription ([`RawSink`], host → backend):
//!   the backend delivers a message object of the sink's table through it, or reports why
//!   it dropped one. The host counts both.
//! - A **publication** ([`RawPublication`], host → backend) is one published message with
//!   its context, borrowed for the duration of the backend's `publish` call.
//!
//! Contexts cross as borrowed lists of key/value views ([`MetaView`]).

use std::ffi::c_void;
use std::marker::PhantomData;
use std::sync::Arc;

use super::channel::TypeSupportVtable;
use super::context::with_module_tag;
use super::{contain, ErrorSink, ErrorSlot, Header, RawMessage, Status, StrView};
use crate::channel::{Context, ContextKind, DropReason, Message};

/// One key/value pair of a context, borrowed for `'a`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct MetaPair<'a> {
    key: StrView,
    value: StrView,
    _life: PhantomData<&'a str>,
}

impl<'a> MetaPair<'a> {
    /// A pair of views of `key` and `value`.
    #[inline]
    pub fn new(key: &'a str, value: &'a str) -> MetaPair<'a> {
        MetaPair {
            key: StrView::new(key),
            value: StrView::new(value),
            _life: PhantomData,
        }
    }

    /// The key (empty if it is not UTF-8).
    #[inline]
    pub fn key(&self) -> &'a str {
        // SAFETY: a pair is made from `&'a str`s (`new`) or handed over by the ABI for a
        // call, during which it is borrowed (`MetaView::pairs`).
        unsafe { self.key.as_str() }.unwrap_or("")
    }

    /// The value (empty if it is not UTF-8).
    #[inline]
    pub fn value(&self) -> &'a str {
        // SAFETY: as in `key`.
        unsafe { self.value.as_str() }.unwrap_or("")
    }

    /// Whether the key is `key` (compared as bytes: no UTF-8 check).
    #[inline]
    pub fn is_key(&self, key: &str) -> bool {
        self.bytes().0 == key.as_bytes()
    }

    /// A pair of views of bytes that may not be UTF-8 (as a foreign caller may hand
    /// over); `key` and `value` read such a part as empty.
    pub(crate) fn from_bytes(key: &'a [u8], value: &'a [u8]) -> MetaPair<'a> {
        let view = |b: &[u8]| StrView {
            ptr: b.as_ptr(),
            len: b.len(),
        };
        MetaPair {
            key: view(key),
            value: view(value),
            _life: PhantomData,
        }
    }

    /// The key's and the value's bytes, not checked as UTF-8: for writing a pair out or
    /// comparing it, where [`key`](Self::key) and [`value`](Self::value) would check.
    ///
    /// ```
    /// use aimrt_plugin_api::ffi::MetaPair;
    /// let pair = MetaPair::new("k", "v");
    /// assert_eq!(pair.bytes(), (&b"k"[..], &b"v"[..]));
    /// ```
    #[inline]
    pub fn bytes(&self) -> (&'a [u8], &'a [u8]) {
        // SAFETY: as in `key`.
        unsafe { (self.key.as_bytes(), self.value.as_bytes()) }
    }
}

/// A borrowed list of key/value pairs: a context crossing the ABI.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct MetaView {
    /// The first pair (may dangle when `len == 0`).
    pub ptr: *const MetaPair<'static>,
    /// The number of pairs.
    pub len: usize,
}

impl MetaView {
    /// A view of `pairs`, valid as long as they are.
    pub fn new(pairs: &[MetaPair<'_>]) -> MetaView {
        MetaView {
            ptr: pairs.as_ptr().cast(),
            len: pairs.len(),
        }
    }

    /// The pairs.
    ///
    /// # Safety
    /// The list and every view in it must be readable for `'a`.
    #[inline]
    pub unsafe fn pairs<'a>(self) -> &'a [MetaPair<'a>] {
        if self.len == 0 || self.ptr.is_null() {
            return &[];
        }
        // SAFETY: non-null and readable for `len` pairs per the caller's guarantee.
        unsafe { std::slice::from_raw_parts(self.ptr.cast(), self.len) }
    }
}

/// Pairs of views of `ctx`'s entries.
// Inlined and pushed one by one: built where the caller keeps it, per message, rather than
// collected by `SmallVec`'s generic `extend` and moved out.
#[inline]
pub fn meta_of<'a>(ctx: impl Iterator<Item = (&'a str, &'a str)>) -> MetaPairs<'a> {
    ctx.map(|(k, v)| MetaPair::new(k, v)).collect()
}

/// The pairs [`meta_of`] makes: up to 8 on the stack (a context has a handful of pairs:
/// AimRT's framework keys and the user's), more on the heap. It derefs to a slice.
///
/// ```
/// use aimrt_plugin_api::ffi::meta_of;
/// let pairs = meta_of([("aimrt-backend", "http")].into_iter());
/// assert_eq!(pairs.len(), 1);
/// assert_eq!(pairs[0].key(), "aimrt-backend");
/// ```
#[derive(Debug, Default, Clone)]
pub struct MetaPairs<'a>(smallvec::SmallVec<[MetaPair<'a>; 8]>);

impl<'a> MetaPairs<'a> {
    /// Adds `pair` last (whether or not its key is there).
    #[inline]
    pub fn push(&mut self, pair: MetaPair<'a>) {
        self.0.push(pair);
    }

    /// Sets `key` to `value`: in place when the key is there, else last.
    ///
    /// ```
    /// use aimrt_plugin_api::ffi::meta_of;
    /// let mut pairs = meta_of([("a", "1"), ("b", "2")].into_iter());
    /// pairs.set("a", "3");
    /// pairs.set("c", "4");
    /// let all: Vec<_> = pairs.iter().map(|p| (p.key(), p.value())).collect();
    /// assert_eq!(all, [("a", "3"), ("b", "2"), ("c", "4")]);
    /// ```
    #[inline]
    pub fn set(&mut self, key: &'a str, value: &'a str) {
        match self.0.iter_mut().find(|p| p.is_key(key)) {
            Some(pair) => *pair = MetaPair::new(key, value),
            None => self.0.push(MetaPair::new(key, value)),
        }
    }
}

impl<'a> Extend<MetaPair<'a>> for MetaPairs<'a> {
    /// Adds each pair last: how a per-message list is built in place (returning one from
    /// a function copies its few hundred bytes).
    #[inline]
    fn extend<I: IntoIterator<Item = MetaPair<'a>>>(&mut self, pairs: I) {
        for pair in pairs {
            self.push(pair);
        }
    }
}

impl<'a> FromIterator<MetaPair<'a>> for MetaPairs<'a> {
    #[inline]
    fn from_iter<I: IntoIterator<Item = MetaPair<'a>>>(pairs: I) -> Self {
        let mut out = MetaPairs::default();
        out.extend(pairs);
        out
    }
}

impl<'a> std::ops::Deref for MetaPairs<'a> {
    type Target = [MetaPair<'a>];

    #[inline]
    fn deref(&self) -> &[MetaPair<'a>] {
        &self.0
    }
}

/// The pairs of a context handed to a module's subscriber, read in place for the length
/// of one call instead of copied: what a subscribe [`Context`] holds until something
/// changes or clones it (then it copies them, [`Meta`](crate::meta::Meta)).
#[derive(Clone, Copy)]
pub(crate) struct LentPairs(MetaView);

// SAFETY: a read-only view of bytes that stay unchanged while it exists (`new`); reading
// them from another thread during that time is as safe as from this one.
unsafe impl Send for LentPairs {}
// SAFETY: see `Send`: nothing is written through it.
unsafe impl Sync for LentPairs {}

impl LentPairs {
    /// Lends the pairs of `view`.
    ///
    /// # Safety
    /// The list and every view in it must stay readable and unchanged as long as the
    /// value or any copy of it exists. Only [`run_callback`] makes one, for a context
    /// that lives in its frame and that callbacks get by reference.
    unsafe fn new(view: MetaView) -> LentPairs {
        LentPairs(view)
    }

    /// The pairs.
    pub(crate) fn pairs(&self) -> &[MetaPair<'_>] {
        // SAFETY: readable while `self` exists (`new`'s contract), which outlives the
        // borrow of `self`.
        unsafe { self.0.pairs() }
    }
}

impl std::fmt::Debug for LentPairs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list()
            .entries(self.pairs().iter().map(|p| (p.key(), p.value())))
            .finish()
    }
}

// ---- the module's subscriber (module → host) --------------------------------------------

/// A module's subscription callback.
#[repr(C)]
pub struct RawSubscriber {
    /// The operations.
    pub vtable: *const SubscriberVtable,
    /// The module's object.
    pub obj: *const c_void,
}

// SAFETY: subscriber objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawSubscriber {}
// SAFETY: see `Send`.
unsafe impl Sync for RawSubscriber {}

/// Subscriber operations.
#[repr(C)]
pub struct SubscriberVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Handles one message. `msg` is one reference to an object of the table the module
    /// subscribed with; the callee takes it over. Not OK, with a message: `FAILED` the
    /// callback panicked; `QUEUE_FULL`/`SHUT_DOWN` the executor of an async subscriber
    /// refused its task.
    pub call: unsafe extern "C" fn(
        obj: *const c_void,
        ctx: MetaView,
        msg: *const c_void,
        err: ErrorSink,
    ) -> Status,
    /// Frees the subscriber.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
}

/// A subscription callback: the subscribe context (lent for the call: a callback that
/// keeps it clones it) and the message; `Err` says why the message was not handled.
pub(crate) type Callback<M> =
    dyn Fn(&Context, Arc<M>) -> Result<(), (DropReason, String)> + Send + Sync;

struct SubscriberObj<M: Message> {
    callback: Box<Callback<M>>,
    /// Whether the callback reads its context: when not, it gets an empty one.
    context: bool,
    /// The module that subscribed: its logger serves lines of the callback.
    module_tag: usize,
}

struct SubscriberExport<M>(PhantomData<M>);

impl<M: Message> SubscriberExport<M> {
    const VTABLE: SubscriberVtable = SubscriberVtable {
        header: Header::of::<SubscriberVtable>(),
        call: Self::call,
        drop: Self::drop,
    };

    unsafe extern "C" fn call(
        obj: *const c_void,
        ctx: MetaView,
        msg: *const c_void,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: `obj` is a live `SubscriberObj<M>` (vtable contract); `msg` is one
        // reference to an `Arc<M>` of this library's `M` table, which we take over.
        let (s, msg) = unsafe {
            (
                &*obj.cast::<SubscriberObj<M>>(),
                Arc::from_raw(msg.cast::<M>()),
            )
        };
        let ctx = s.context.then_some(ctx);
        // SAFETY: the views are valid for this call.
        unsafe { run_callback(s.module_tag, ctx, err, |ctx| (s.callback)(ctx, msg)) }
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: `obj` came from `Box::into_raw` in `new`; this is its last use.
        let s = unsafe { Box::from_raw(obj.cast::<SubscriberObj<M>>().cast_mut()) };
        let _ = contain(move || drop(s));
    }
}

/// Runs a subscriber's callback with the subscribe context of `ctx` (an empty one for
/// `None`), in the logging context of the module that subscribed: OK, or the reason it
/// did not handle the message (`QUEUE_FULL` when its executor refused it, `FAILED` when
/// it failed or panicked).
///
/// The context reads the pairs in place ([`LentPairs`]): it lives in this frame and the
/// callback gets it by reference, so it cannot outlive the call; a callback that keeps
/// it (an async subscriber) clones it, which copies the pairs.
///
/// # Safety
/// `ctx` is valid for the call.
unsafe fn run_callback(
    module_tag: usize,
    ctx: Option<MetaView>,
    err: ErrorSink,
    callback: impl FnOnce(&Context) -> Result<(), (DropReason, String)>,
) -> Status {
    let ctx = match ctx {
        // SAFETY: the view is valid for the call (the contract), and the context that
        // holds it is dropped at the end of this function; `callback` only borrows it.
        Some(ctx) => Context::lent(ContextKind::Subscribe, unsafe { LentPairs::new(ctx) }),
        None => Context::new(ContextKind::Subscribe),
    };
    match with_module_tag(module_tag as *const c_void, || contain(|| callback(&ctx))) {
        Ok(Ok(())) => Status::OK,
        Ok(Err((reason, why))) => {
            err.report(&why);
            if reason == DropReason::Refused {
                Status::QUEUE_FULL
            } else {
                Status::FAILED
            }
        }
        Err(why) => {
            err.report(&why);
            Status::FAILED
        }
    }
}

/// A subscription callback for messages of any table, as [`RawMessage`]s.
pub(crate) type RawCallback = dyn Fn(&Context, RawMessage) -> Result<(), String> + Send + Sync;

struct RawSubscriberObj {
    ts: &'static TypeSupportVtable,
    callback: Box<RawCallback>,
    module_tag: usize,
}

struct RawSubscriberExport;

impl RawSubscriberExport {
    const VTABLE: SubscriberVtable = SubscriberVtable {
        header: Header::of::<SubscriberVtable>(),
        call: Self::call,
        drop: Self::drop,
    };

    unsafe extern "C" fn call(
        obj: *const c_void,
        ctx: MetaView,
        msg: *const c_void,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: `obj` is a live `RawSubscriberObj` (vtable contract); `msg` is one
        // reference to an object of the table the subscription was made with, which we
        // take over.
        let (s, msg) = unsafe {
            let s = &*obj.cast::<RawSubscriberObj>();
            (s, RawMessage::from_raw(s.ts, msg))
        };
        // SAFETY: the views are valid for this call.
        unsafe {
            run_callback(s.module_tag, Some(ctx), err, |ctx| {
                (s.callback)(ctx, msg).map_err(|why| (DropReason::SubscriberFailed, why))
            })
        }
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: `obj` came from `Box::into_raw` in `raw`; this is its last use.
        let s = unsafe { Box::from_raw(obj.cast::<RawSubscriberObj>().cast_mut()) };
        let _ = contain(move || drop(s));
    }
}

impl RawSubscriber {
    /// Exports `callback` for messages of the table `ts` (any library's), attributed to
    /// the current module: for plugins that handle messages by type name.
    pub(crate) fn raw(ts: &'static TypeSupportVtable, callback: Box<RawCallback>) -> RawSubscriber {
        let obj = RawSubscriberObj {
            ts,
            callback,
            module_tag: super::context::current_module_tag() as usize,
        };
        RawSubscriber {
            vtable: &RawSubscriberExport::VTABLE,
            obj: Box::into_raw(Box::new(obj)).cast(),
        }
    }

    /// Exports `callback` for messages of `M`, attributed to the current module.
    /// `context`: whether the callback reads its context (else it gets an empty one).
    pub(crate) fn new<M: Message>(callback: Box<Callback<M>>, context: bool) -> RawSubscriber {
        let obj = SubscriberObj {
            callback,
            context,
            module_tag: super::context::current_module_tag() as usize,
        };
        RawSubscriber {
            vtable: &SubscriberExport::<M>::VTABLE,
            obj: Box::into_raw(Box::new(obj)).cast(),
        }
    }

    /// Calls the subscriber with `ctx` and `msg`, which must be an object of the table the
    /// subscriber was made for (host use). `Err`: why it was not handled.
    pub fn call(&self, ctx: &[MetaPair<'_>], msg: RawMessage) -> Result<(), (DropReason, String)> {
        let (_, ptr) = msg.into_raw();
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; the views and the sink outlive the call; the reference to
        // `ptr` passes to the callee.
        let status =
            unsafe { ((*self.vtable).call)(self.obj, MetaView::new(ctx), ptr, slot.sink()) };
        let reason = match status {
            Status::QUEUE_FULL | Status::SHUT_DOWN => DropReason::Refused,
            _ => DropReason::SubscriberFailed,
        };
        slot.result(status).map_err(|why| (reason, why))
    }
}

impl Drop for RawSubscriber {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { ((*self.vtable).drop)(self.obj) }
    }
}

// ---- the host's sink (host → backend) ----------------------------------------------------

/// One subscription as a backend sees it: where it delivers messages.
#[repr(C)]
pub struct RawSink {
    /// The operations.
    pub vtable: *const SinkVtable,
    /// The host's object.
    pub obj: *const c_void,
}

// SAFETY: sink objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawSink {}
// SAFETY: see `Send`.
unsafe impl Sync for RawSink {}

/// Sink operations.
#[repr(C)]
pub struct SinkVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The subscriber's message table: a delivered message must be an object of it.
    pub type_support: unsafe extern "C" fn(obj: *const c_void) -> *const TypeSupportVtable,
    /// Delivers one message: `msg` is one reference to an object of `type_support`, which
    /// the sink takes over. Not OK: the subscriber failed (already counted and logged).
    pub deliver: unsafe extern "C" fn(
        obj: *const c_void,
        ctx: MetaView,
        msg: *const c_void,
        err: ErrorSink,
    ) -> Status,
    /// Reports a message the backend could not deliver ([`DropReason`] code and details).
    pub report_drop: unsafe extern "C" fn(obj: *const c_void, reason: u32, details: StrView),
    /// Adds a reference to the sink.
    pub retain: unsafe extern "C" fn(obj: *const c_void),
    /// Drops a reference to the sink.
    pub release: unsafe extern "C" fn(obj: *const c_void),
    /// Reports `count` messages the backend could not deliver at once, for one reason
    /// (1.12): e.g. a gap in a publisher's sequence that a transport saw.
    pub report_drops:
        unsafe extern "C" fn(obj: *const c_void, reason: u32, count: u64, details: StrView),
}

/// Where a sink table's `report_drops` entry (1.12) ends.
const REPORT_DROPS_END: usize = std::mem::offset_of!(SinkVtable, report_drops) + size_of::<usize>();

/// What the runtime implements behind a sink.
pub trait SinkHost: Send + Sync + 'static {
    /// The subscriber's message table.
    fn type_support(&self) -> &'static TypeSupportVtable;
    /// Runs the subscriber on `msg` (an object of `type_support`).
    fn deliver(&self, ctx: &[MetaPair<'_>], msg: RawMessage) -> Result<(), String>;
    /// Counts and reports a message the backend dropped.
    fn report_drop(&self, reason: DropReason, details: &str);
    /// Counts and reports `count` messages the backend dropped, for one reason.
    fn report_drops(&self, reason: DropReason, count: u64, details: &str);
}

struct SinkExport<S>(PhantomData<S>);

impl<S: SinkHost> SinkExport<S> {
    const VTABLE: SinkVtable = SinkVtable {
        header: Header::of::<SinkVtable>(),
        type_support: Self::type_support,
        deliver: Self::deliver,
        report_drop: Self::report_drop,
        retain: super::arc_retain::<S>,
        release: super::arc_release::<S>,
        report_drops: Self::report_drops,
    };

    /// # Safety
    /// `obj` is a live `Arc<S>` pointer of `RawSink::new::<S>`.
    unsafe fn get<'a>(obj: *const c_void) -> &'a S {
        // SAFETY: per the contract.
        unsafe { &*obj.cast::<S>() }
    }

    unsafe extern "C" fn type_support(obj: *const c_void) -> *const TypeSupportVtable {
        // SAFETY: live sink (vtable contract).
        unsafe { Self::get(obj) }.type_support()
    }

    unsafe extern "C" fn deliver(
        obj: *const c_void,
        ctx: MetaView,
        msg: *const c_void,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live sink; `msg` is one reference to an object of the sink's table.
        let (s, msg) = unsafe {
            let s = Self::get(obj);
            (s, RawMessage::from_raw(s.type_support(), msg))
        };
        // SAFETY: the views are valid for this call.
        let ctx = unsafe { ctx.pairs() };
        match contain(|| s.deliver(ctx, msg)) {
            Ok(Ok(())) => Status::OK,
            Ok(Err(why)) | Err(why) => {
                err.report(&why);
                Status::FAILED
            }
        }
    }

    unsafe extern "C" fn report_drop(obj: *const c_void, reason: u32, details: StrView) {
        // SAFETY: live sink; the view is valid for this call.
        let (s, details) = unsafe { (Self::get(obj), details.to_string_lossy()) };
        let reason = DropReason::from_code(reason);
        let _ = contain(|| s.report_drop(reason, &details));
    }

    unsafe extern "C" fn report_drops(
        obj: *const c_void,
        reason: u32,
        count: u64,
        details: StrView,
    ) {
        // SAFETY: live sink; the view is valid for this call.
        let (s, details) = unsafe { (Self::get(obj), details.to_string_lossy()) };
        let reason = DropReason::from_code(reason);
        let _ = contain(|| s.report_drops(reason, count, &details));
    }
}

impl RawSink {
    /// Exports `sink` (host use); the result owns one reference.
    pub fn new<S: SinkHost>(sink: Arc<S>) -> RawSink {
        RawSink {
            vtable: &SinkExport::<S>::VTABLE,
            obj: Arc::into_raw(sink).cast(),
        }
    }

    fn vt(&self) -> &SinkVtable {
        // SAFETY: sink vtables are static data of the host, which is never unloaded.
        unsafe { &*self.vtable }
    }

    /// The subscriber's message table.
    pub fn type_support(&self) -> &'static TypeSupportVtable {
        // SAFETY: live sink; tables are static data of never-unloaded libraries.
        unsafe { &*(self.vt().type_support)(self.obj) }
    }

    /// Delivers `msg`, an object of [`type_support`](RawSink::type_support).
    pub fn deliver(&self, ctx: &[MetaPair<'_>], msg: RawMessage) -> Result<(), String> {
        if !std::ptr::eq(msg.type_support(), self.type_support()) {
            let reason = format!(
                "a backend delivered a '{}' object made by another library; decode it with the sink's type support",
                super::type_name_of(msg.type_support())
            );
            self.report_drop(DropReason::DecodeFailed, &reason);
            return Err(reason);
        }
        let (_, ptr) = msg.into_raw();
        let mut slot = ErrorSlot::default();
        // SAFETY: live sink; the reference to `ptr` (an object of the sink's table) passes
        // to the sink; the views and the error sink outlive the call.
        let status = unsafe { (self.vt().deliver)(self.obj, MetaView::new(ctx), ptr, slot.sink()) };
        slot.result(status)
    }

    /// Reports a message that could not be delivered (counted by the runtime).
    pub fn report_drop(&self, reason: DropReason, details: &str) {
        // SAFETY: live sink; the view outlives the call.
        unsafe { (self.vt().report_drop)(self.obj, reason.code(), StrView::new(details)) }
    }

    /// Reports `count` messages that could not be delivered, for one reason (counted by
    /// the runtime). A host table without the entry (older than 1.12, which refuses a
    /// library of 1.12, so only a hand-made table) gets one report of the first message.
    pub fn report_drops(&self, reason: DropReason, count: u64, details: &str) {
        if count == 0 {
            return;
        }
        let vt = self.vt();
        if !vt.header.has(REPORT_DROPS_END) {
            return self.report_drop(reason, details);
        }
        // SAFETY: live sink; the table has the entry (size checked); the view outlives
        // the call.
        unsafe { (vt.report_drops)(self.obj, reason.code(), count, StrView::new(details)) }
    }
}

impl Clone for RawSink {
    fn clone(&self) -> RawSink {
        // SAFETY: live sink; one more reference.
        unsafe { (self.vt().retain)(self.obj) };
        RawSink {
            vtable: self.vtable,
            obj: self.obj,
        }
    }
}

impl Drop for RawSink {
    fn drop(&mut self) {
        // SAFETY: we own one reference.
        unsafe { (self.vt().release)(self.obj) }
    }
}

impl std::fmt::Debug for RawSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawSink")
            .field("type", &super::type_name_of(self.type_support()))
            .finish()
    }
}

// ---- a publication (host → backend) ------------------------------------------------------

/// One published message as the backends see it; everything is borrowed for the duration
/// of the backend's `publish` call (a backend that keeps the message takes a reference).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct RawPublication {
    /// Size and minor of this struct.
    pub header: Header,
    /// The topic.
    pub topic: StrView,
    /// The context, with `aimrt-serialization_type`, `aimrt-pub_seq` and `aimrt-pub_ts`
    /// set by the runtime.
    pub ctx: MetaView,
    /// The message's table (the publisher's library).
    pub type_support: *const TypeSupportVtable,
    /// The message object (borrowed).
    pub msg: *const c_void,
    /// The publishing module's pkg path (`registered in code` for in-code modules).
    pub pkg: StrView,
    /// The publishing module.
    pub module: StrView,
    /// The topic, for reporting a message this backend took and lost later (ABI 1.8;
    /// [`RawTopicRef::NONE`] where no topic counts it, as in a filter's publication).
    pub topic_ref: RawTopicRef,
}

impl RawPublication {
    /// The end of [`topic_ref`](Self::topic_ref): a publication of a host of ABI 1.7 or
    /// older is shorter.
    const TOPIC_REF_END: usize =
        std::mem::offset_of!(RawPublication, topic_ref) + size_of::<RawTopicRef>();

    /// A counted reference to the publication's topic, if the host gave one (backend use).
    pub fn topic_handle(&self) -> Option<TopicHandle> {
        if !self.header.has(Self::TOPIC_REF_END) || self.topic_ref.vtable.is_null() {
            return None;
        }
        // SAFETY: a host of ABI 1.8 fills `topic_ref` with a live topic and its table
        // (or null, checked above) for the duration of `publish`; `retain` adds the
        // reference the handle owns.
        unsafe { ((*self.topic_ref.vtable).retain)(self.topic_ref.obj) };
        Some(TopicHandle {
            raw: self.topic_ref,
        })
    }
}

// ---- a publication's topic (host → backend, ABI 1.8) ------------------------------------

/// A publication's topic as a backend sees it, borrowed in a [`RawPublication`]: what a
/// backend tells when a message it took in `publish` is lost afterwards (a send error, a
/// queue given up at shutdown). [`TopicHandle`] holds a reference.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct RawTopicRef {
    /// The operations (null: no topic).
    pub vtable: *const TopicRefVtable,
    /// The host's object.
    pub obj: *const c_void,
}

impl RawTopicRef {
    /// No topic: reports go nowhere.
    pub const NONE: RawTopicRef = RawTopicRef {
        vtable: std::ptr::null(),
        obj: std::ptr::null(),
    };

    /// Borrows `topic` for one publication (host use): valid while `topic` lives.
    pub fn borrow<T: TopicHost>(topic: &Arc<T>) -> RawTopicRef {
        RawTopicRef {
            vtable: &TopicExport::<T>::VTABLE,
            obj: Arc::as_ptr(topic).cast(),
        }
    }
}

/// Topic operations (ABI 1.8).
#[repr(C)]
pub struct TopicRefVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// Counts one message as dropped ([`DropReason`] code) with details for the log.
    pub report_drop: unsafe extern "C" fn(obj: *const c_void, reason: u32, details: StrView),
    /// Adds a reference to the topic.
    pub retain: unsafe extern "C" fn(obj: *const c_void),
    /// Drops a reference to the topic.
    pub release: unsafe extern "C" fn(obj: *const c_void),
}

/// What the runtime implements behind a topic reference.
pub trait TopicHost: Send + Sync + 'static {
    /// Counts and reports a message a backend dropped after `publish` took it.
    fn report_drop(&self, reason: DropReason, details: &str);
}

struct TopicExport<T>(PhantomData<T>);

impl<T: TopicHost> TopicExport<T> {
    const VTABLE: TopicRefVtable = TopicRefVtable {
        header: Header::of::<TopicRefVtable>(),
        report_drop: Self::report_drop,
        retain: super::arc_retain::<T>,
        release: super::arc_release::<T>,
    };

    unsafe extern "C" fn report_drop(obj: *const c_void, reason: u32, details: StrView) {
        // SAFETY: a live `Arc<T>` pointer (vtable contract); the view is valid for this call.
        let (t, details) = unsafe { (&*obj.cast::<T>(), details.to_string_lossy()) };
        let reason = DropReason::from_code(reason);
        let _ = contain(|| t.report_drop(reason, &details));
    }
}

/// A counted reference to a publication's topic (backend use): clone it into whatever
/// carries the message on, and report through it if the message is lost.
pub struct TopicHandle {
    raw: RawTopicRef,
}

// SAFETY: topic objects are `Send + Sync` (`TopicHost` requires it).
unsafe impl Send for TopicHandle {}
// SAFETY: see `Send`.
unsafe impl Sync for TopicHandle {}

impl TopicHandle {
    /// Counts one message as dropped for `reason` in the topic's stats.
    pub fn report_drop(&self, reason: DropReason, details: &str) {
        // SAFETY: we hold a reference to a live topic; the view outlives the call.
        unsafe {
            ((*self.raw.vtable).report_drop)(self.raw.obj, reason.code(), StrView::new(details))
        }
    }
}

impl Clone for TopicHandle {
    fn clone(&self) -> TopicHandle {
        // SAFETY: we hold a reference to a live topic; one more.
        unsafe { ((*self.raw.vtable).retain)(self.raw.obj) };
        TopicHandle { raw: self.raw }
    }
}

impl Drop for TopicHandle {
    fn drop(&mut self) {
        // SAFETY: we own one reference.
        unsafe { ((*self.raw.vtable).release)(self.raw.obj) }
    }
}

impl std::fmt::Debug for TopicHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("TopicHandle")
    }
}

// ---- counters ----------------------------------------------------------------------------

/// The counters of a topic as they cross the ABI.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct RawTopicStats {
    /// Size and minor of this struct.
    pub header: Header,
    /// Messages accepted by `publish`.
    pub published: u64,
    /// Subscriber callbacks that completed.
    pub delivered: u64,
    /// Drops per [`DropReason`] code (room for reasons added later).
    pub dropped: [u64; 16],
}

impl RawTopicStats {
    /// All zero.
    pub const fn zero() -> RawTopicStats {
        RawTopicStats {
            header: Header::of::<RawTopicStats>(),
            published: 0,
            delivered: 0,
            dropped: [0; 16],
        }
    }

    /// From the safe form.
    pub fn of(stats: &crate::channel::TopicStats) -> RawTopicStats {
        let mut raw = RawTopicStats::zero();
        raw.published = stats.published;
        raw.delivered = stats.delivered;
        for (reason, n) in &stats.dropped {
            if let Some(slot) = raw.dropped.get_mut(reason.code() as usize) {
                *slot += n;
            }
        }
        raw
    }

    /// To the safe form.
    pub fn to_stats(&self) -> crate::channel::TopicStats {
        let mut dropped: Vec<(DropReason, u64)> = Vec::new();
        for (code, &n) in self.dropped.iter().enumerate() {
            if n == 0 {
                continue;
            }
            let reason = DropReason::from_code(code as u32);
            match dropped.iter_mut().find(|(r, _)| *r == reason) {
                Some((_, total)) => *total += n,
                None => dropped.push((reason, n)),
            }
        }
        crate::channel::TopicStats {
            published: self.published,
            delivered: self.delivered,
            dropped,
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::*;
    use crate::ffi::channel::tests::Probe;

    /// What a subscriber of `context` sees of a delivery with one pair.
    fn seen(context: bool) -> Vec<(String, String)> {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let to = seen.clone();
        let callback: Box<Callback<Probe>> = Box::new(move |ctx, msg| {
            assert_eq!(msg.n, 7);
            let pairs = ctx.iter().map(|(k, v)| (k.to_owned(), v.to_owned()));
            to.lock().unwrap().extend(pairs);
            Ok(())
        });
        let sub = RawSubscriber::new(callback, context);
        let pairs = meta_of([("k", "v")].into_iter());
        sub.call(&pairs, RawMessage::new(Arc::new(Probe { n: 7 })))
            .expect("handled");
        let out = seen.lock().unwrap().clone();
        out
    }

    #[test]
    fn a_subscriber_that_reads_no_context_gets_an_empty_one_and_others_the_pairs() {
        assert_eq!(seen(true), [("k".to_owned(), "v".to_owned())]);
        assert!(seen(false).is_empty());
    }

    /// Pairs over `text`: `k1=v1`, a key that is not UTF-8, an `aimrt-` key, `k2=` a value
    /// cut inside a character.
    fn pairs_over(text: &[u8]) -> MetaPairs<'_> {
        let at = |a: usize, b: usize| &text[a..b];
        MetaPairs(
            [
                MetaPair::from_bytes(at(0, 2), at(2, 4)),
                MetaPair::from_bytes(b"\xff", at(2, 4)),
                MetaPair::from_bytes(b"aimrt-backend", b"zenoh"),
                MetaPair::from_bytes(at(4, 6), "\u{e9}".as_bytes().get(..1).unwrap_or_default()),
            ]
            .into_iter()
            .collect(),
        )
    }

    #[test]
    fn a_lent_context_reads_as_its_copy_and_a_change_or_clone_copies_it_first() {
        use crate::meta::Meta;
        let text = b"k1v1k2".to_vec();
        let pairs = pairs_over(&text);
        // SAFETY: `pairs` and `text` outlive every use of the view and the metas below
        // that hold it (all dropped before them).
        let view = unsafe { LentPairs::new(MetaView::new(&pairs)) };
        let lent = Meta::lent(view);
        let copy = Meta::from_abi(&pairs);
        let all = |m: &Meta| {
            m.iter()
                .map(|(k, v)| (k.to_owned(), v.to_owned()))
                .collect::<Vec<_>>()
        };
        let expected = [
            ("k1", "v1"),
            ("", "v1"),
            ("aimrt-backend", "zenoh"),
            ("k2", ""),
        ]
        .map(|(k, v)| (k.to_owned(), v.to_owned()));
        assert_eq!(all(&lent), expected);
        assert_eq!(all(&copy), expected);
        assert_eq!(lent, copy);
        assert_eq!(lent.len(), 4);
        assert_eq!(lent.get("k1"), Some("v1"));
        assert_eq!(lent.get("k2"), Some(""));
        assert_eq!(lent.get("nope"), None);
        let users: Vec<_> = lent.iter_unless(|k| k.starts_with(b"aimrt-")).collect();
        assert_eq!(users, [("k1", "v1"), ("", "v1"), ("k2", "")]);
        // A change copies the pairs first, then applies.
        let mut changed = Meta::lent(view);
        changed.set("k1", "new");
        changed.push("k3", "3");
        assert_eq!(changed.remove("aimrt-backend").as_deref(), Some("zenoh"));
        assert!(!changed.is_lent());
        assert_eq!(
            changed.iter().collect::<Vec<_>>(),
            [("k1", "new"), ("", "v1"), ("k2", ""), ("k3", "3")]
        );
        let mut cleared = Meta::lent(view);
        cleared.clear();
        assert_eq!(cleared.len(), 0);
        assert_eq!(cleared.iter().count(), 0);
        // A clone owns its pairs: it reads the same once the lent bytes are gone.
        let kept = lent.clone();
        assert!(!kept.is_lent());
        drop((lent, changed, pairs));
        drop(text);
        assert_eq!(all(&kept), expected);
    }

    #[test]
    fn a_context_kept_past_the_delivery_owns_its_pairs() {
        let kept = Arc::new(Mutex::new(Vec::new()));
        let to = kept.clone();
        // As an async subscriber: the context goes on after the call returns.
        let callback: Box<Callback<Probe>> = Box::new(move |ctx, _| {
            to.lock().unwrap().push(ctx.clone());
            Ok(())
        });
        let sub = RawSubscriber::new(callback, true);
        let mut text = b"k1v1k2".to_vec();
        {
            let pairs = pairs_over(&text);
            sub.call(&pairs, RawMessage::new(Arc::new(Probe { n: 1 })))
                .expect("handled");
        }
        // The delivery's bytes change after it (every byte becomes `z`): the kept context
        // must not see that.
        text.fill(b'z');
        let kept = kept.lock().unwrap();
        let ctx = &kept[0];
        assert_eq!(ctx.get("k1"), Some("v1"));
        assert_eq!(ctx.kind(), ContextKind::Subscribe);
        assert_eq!(
            ctx.to_string(),
            r#"Subscriber context, meta: {{"k1":"v1"},{"":"v1"},{"aimrt-backend":"zenoh"},{"k2":""}}"#
        );
        let mut publish = Context::new(ContextKind::Publish);
        publish.merge_from(ctx);
        assert_eq!(
            publish.iter().collect::<Vec<_>>(),
            [("k1", "v1"), ("", "v1"), ("k2", "")]
        );
    }

    /// A sink that keeps what a backend reports.
    #[derive(Default)]
    struct Reports(Mutex<Vec<(DropReason, u64, String)>>);

    impl SinkHost for Reports {
        fn type_support(&self) -> &'static TypeSupportVtable {
            crate::ffi::type_support::<Probe>()
        }
        fn deliver(&self, _: &[MetaPair<'_>], _: RawMessage) -> Result<(), String> {
            Ok(())
        }
        fn report_drop(&self, reason: DropReason, details: &str) {
            self.0.lock().unwrap().push((reason, 1, details.to_owned()));
        }
        fn report_drops(&self, reason: DropReason, count: u64, details: &str) {
            self.0
                .lock()
                .unwrap()
                .push((reason, count, details.to_owned()));
        }
    }

    #[test]
    fn many_drops_cross_as_one_report_and_a_table_of_1_11_gets_the_first() {
        let host = Arc::new(Reports::default());
        let sink = RawSink::new(host.clone());
        sink.report_drops(DropReason::Lost, 3942, "a gap");
        sink.report_drops(DropReason::Lost, 0, "nothing");
        assert_eq!(
            *host.0.lock().unwrap(),
            [(DropReason::Lost, 3942, "a gap".to_owned())]
        );

        // A table of 1.11's size ends before `report_drops`: one message is reported.
        host.0.lock().unwrap().clear();
        let v = sink.vt();
        let old = SinkVtable {
            header: Header {
                size: std::mem::offset_of!(SinkVtable, report_drops) as u32,
                abi_minor: 11,
            },
            type_support: v.type_support,
            deliver: v.deliver,
            report_drop: v.report_drop,
            retain: v.retain,
            release: v.release,
            report_drops: v.report_drops,
        };
        let old = RawSink {
            vtable: Box::leak(Box::new(old)),
            obj: sink.obj,
        };
        // `old` holds no reference of its own: it must not release one.
        let old = std::mem::ManuallyDrop::new(old);
        old.report_drops(DropReason::Lost, 12, "a gap");
        assert_eq!(
            *host.0.lock().unwrap(),
            [(DropReason::Lost, 1, "a gap".to_owned())]
        );
    }
}
