//! The versioned C ABI between the `aimrt_main` host and every shared library.
//!
//! Everything that crosses a library boundary is defined here, by hand, as `#[repr(C)]`
//! data: plain structs of `extern "C"` function pointers plus an opaque object pointer,
//! the shape of AimRT's `aimrt_*_base_t` interfaces. The rules (also in `docs/abi.md`):
//!
//! - **One entry per library**: the static [`LibraryDescriptor`] named
//!   [`ENTRY_SYMBOL`]. It is data, so the host checks magic, ABI major/minor, size,
//!   target and unwind flag before it runs any code of the library.
//! - **Every vtable starts with a [`Header`]** `{size, abi_minor}`; fields are only ever
//!   appended, so either side can tell which entries the other has.
//! - **No Rust-only types cross**: strings and bytes cross as borrowed [`StrView`] /
//!   [`BytesView`]; no `String`, `Vec`, `Box<dyn _>`, `u128` or trait object.
//! - **Whoever allocates frees**, through a `drop`/`destroy` entry of the same vtable.
//!   Errors travel back through an [`ErrorSink`] the caller owns: the callee hands a
//!   borrowed message, the caller copies it.
//! - **Panics never cross**: every `extern "C"` function here that runs user code catches
//!   the panic on its own side and reports it as a [`Status`].
//! - **Libraries are never unloaded.**
//!
//! The safe layer (`ExecutorRef`, `CoreRef`, `Registrar`, …) is built on the "exporter"
//! (trait object → vtable) and "importer" (vtable → safe handle) functions of the
//! submodules; all `unsafe` of the crate lives in this module.

pub(crate) mod channel;
pub(crate) mod channel_backend;
pub(crate) mod context;
pub(crate) mod control;
pub(crate) mod core;
pub(crate) mod executor;
pub(crate) mod filter;
pub(crate) mod library;
pub(crate) mod log_backend;
pub(crate) mod logger;
pub(crate) mod module;
pub(crate) mod plugin;
mod process;
pub(crate) mod pubsub;
pub(crate) mod registrar;
pub(crate) mod rpc;
pub(crate) mod rpc_call;
pub(crate) mod rpc_filter;
pub mod task;

pub use process::{keep_freed_memory, HEAP_ALLOCATION_LIMIT, KEEP_FREED_BYTES};

use std::ffi::c_void;

pub use self::channel::{
    find_table, formats_of, schema_of, type_name_bytes_of, type_name_of, type_support, BytesSink,
    RawMessage, RoomSink, TypeSupportVtable,
};
pub use self::channel_backend::{ChannelBackendVtable, RawChannelBackend};
pub use self::control::{ControlHost, ControlVtable, LevelCallback, RawControl};
pub use self::core::{
    ChannelHandleVtable, CoreVtable, ParameterHandleVtable, RawCore, TextCallback,
};
pub use self::executor::{ExecutorCreateArgs, ExecutorStats, ExecutorVtable, RawExecutor};
pub use self::filter::{
    ChannelFilterVtable, FilterNext, FilterOutcome, RawChannelFilter, RestOfChain,
};
pub use self::library::{HostInit, LibraryDescriptor};
pub use self::log_backend::{
    LogBackendTypeVtable, LogBackendVtable, RawLogBackend, RawLogBackendType, RawLogEntry,
};
pub use self::logger::{LevelWatchers, LevelsChanged, LogRecord, LoggerVtable, RawLogger};
pub use self::module::{ModuleVtable, RawModule, RawModuleInfo};
pub use self::plugin::{PluginInitArgs, PluginVtable, RawPlugin};
pub use self::pubsub::{
    meta_of, MetaPair, MetaPairs, MetaView, RawPublication, RawSink, RawSubscriber, RawTopicRef,
    RawTopicStats, SinkHost, SinkVtable, SubscriberVtable, TopicHandle, TopicHost, TopicRefVtable,
};
pub use self::registrar::{
    ExecutorTypeVtable, RawExecutorType, RawRegistrar, RawThreadFactory, RegistrarVtable,
    ThreadFactoryVtable, ThreadSettings,
};
pub use self::rpc::{
    Completion, HostVtable, RawBackendCall, RawBackendReply, RawHost, RawRpcBackend, RawService,
    RpcBackendVtable, ServiceVtable,
};
pub use self::rpc_call::{
    RawRpcCtx, RawRpcReply, RawServiceFunc, ReplyParts, RpcHandleVtable, ServiceFuncVtable,
    INVOKE_BLOCKING,
};
pub use self::rpc_filter::{
    RawReplyObserver, RawRpcFilter, RawRpcFilterCall, RestOfCall, RpcFilterNext, RpcFilterOutcome,
    RpcFilterVtable,
};
pub use self::task::{RawTask, TaskOps};

/// `b"AIMRTRS\0"` read as a little-endian `u64`: the first field of every descriptor.
pub const MAGIC: u64 = u64::from_le_bytes(*b"AIMRTRS\0");
/// The ABI major version. A library with another major is refused.
pub const ABI_MAJOR: u32 = 1;
/// The ABI minor version. The host accepts libraries whose minor is ≤ its own.
pub const ABI_MINOR: u32 = 13;
/// The name of the one exported symbol of every module or plugin library.
pub const ENTRY_SYMBOL: &str = "aimrt_rs_library";
/// The version of `aimrt-plugin-api` this library was built with.
pub const API_VERSION: &str = env!("CARGO_PKG_VERSION");
/// The target triple this crate was compiled for.
pub const TARGET: &str = env!("AIMRT_TARGET");

/// The first field of every vtable, in both directions.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// `size_of` the whole vtable as its author compiled it.
    pub size: u32,
    /// The ABI minor its author compiled against.
    pub abi_minor: u32,
}

impl Header {
    /// The header for a struct of type `T` built by this crate.
    pub const fn of<T>() -> Self {
        Header {
            size: size_of::<T>() as u32,
            abi_minor: ABI_MINOR,
        }
    }

    /// Whether a vtable with this header has the field that ends at byte `end`.
    pub const fn has(&self, end: usize) -> bool {
        self.size as usize >= end
    }
}

/// Result of every ABI call that can refuse.
#[repr(transparent)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Status(pub u32);

impl Status {
    /// Done.
    pub const OK: Status = Status(0);
    /// The executor's queue is over its `queue_threshold`; the task was dropped.
    pub const QUEUE_FULL: Status = Status(1);
    /// The executor no longer takes work; the task was dropped.
    pub const SHUT_DOWN: Status = Status(2);
    /// A timed call on an executor without timer support; the task was dropped.
    pub const NO_TIMER_SUPPORT: Status = Status(3);
    /// A bad argument or a call in the wrong state; a message went to the error sink.
    pub const INVALID: Status = Status(4);
    /// The callee failed (or panicked); a message went to the error sink.
    pub const FAILED: Status = Status(5);
    /// The named thing does not exist.
    pub const NOT_FOUND: Status = Status(6);
    /// The callee does not implement this call (yet).
    pub const UNSUPPORTED: Status = Status(7);

    /// Whether this is [`Status::OK`].
    pub const fn is_ok(self) -> bool {
        self.0 == 0
    }

    /// The status's name (`"FAILED"`), or `None` for a code this ABI does not define.
    pub const fn name(self) -> Option<&'static str> {
        Some(match self.0 {
            0 => "OK",
            1 => "QUEUE_FULL",
            2 => "SHUT_DOWN",
            3 => "NO_TIMER_SUPPORT",
            4 => "INVALID",
            5 => "FAILED",
            6 => "NOT_FOUND",
            7 => "UNSUPPORTED",
            _ => return None,
        })
    }

    /// What the status means, in a user's words.
    pub const fn meaning(self) -> &'static str {
        match self.0 {
            0 => "done",
            1 => "the executor's queue is over its queue_threshold",
            2 => "the executor no longer takes work",
            3 => "the executor has no timer support",
            4 => "a bad argument or a call in the wrong state",
            5 => "the callee failed or panicked",
            6 => "the named thing does not exist",
            7 => "the callee does not implement this call",
            _ => "a status this version does not know",
        }
    }
}

/// `FAILED (the callee failed or panicked)`; an unknown code prints as `status 42 (…)`.
///
/// ```
/// use aimrt_plugin_api::ffi::Status;
/// assert_eq!(Status::FAILED.to_string(), "FAILED (the callee failed or panicked)");
/// assert_eq!(Status(42).to_string(), "status 42 (a status this version does not know)");
/// ```
impl std::fmt::Display for Status {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.name() {
            Some(name) => write!(f, "{name} ({})", self.meaning()),
            None => write!(f, "status {} ({})", self.0, self.meaning()),
        }
    }
}

/// A borrowed UTF-8 string: pointer and length, not NUL-terminated.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct StrView {
    /// First byte (may dangle when `len == 0`).
    pub ptr: *const u8,
    /// Length in bytes.
    pub len: usize,
}

impl StrView {
    /// A view of `s`; valid as long as `s` is.
    #[inline]
    pub const fn new(s: &str) -> Self {
        StrView {
            ptr: s.as_ptr(),
            len: s.len(),
        }
    }

    /// The empty view.
    pub const EMPTY: StrView = StrView::new("");

    /// Copies the viewed text (invalid UTF-8 is replaced, never trusted).
    ///
    /// # Safety
    /// `ptr..ptr+len` must be readable for the duration of the call.
    pub unsafe fn to_string_lossy(self) -> String {
        // SAFETY: forwarded to the caller.
        unsafe { self.to_str_lossy() }.into_owned()
    }

    /// The viewed text, borrowed when it is valid UTF-8 (invalid bytes are replaced in a
    /// copy, never trusted).
    ///
    /// # Safety
    /// `ptr..ptr+len` must be readable for `'a`.
    pub unsafe fn to_str_lossy<'a>(self) -> std::borrow::Cow<'a, str> {
        // SAFETY: forwarded to the caller.
        lossy(unsafe { self.as_bytes() })
    }

    /// The viewed bytes.
    ///
    /// # Safety
    /// `ptr..ptr+len` must be readable for `'a`.
    #[inline]
    pub unsafe fn as_bytes<'a>(self) -> &'a [u8] {
        if self.len == 0 || self.ptr.is_null() {
            return &[];
        }
        // SAFETY: non-null and readable for `len` bytes per the caller's guarantee.
        unsafe { std::slice::from_raw_parts(self.ptr, self.len) }
    }

    /// The viewed text, if it is UTF-8.
    ///
    /// # Safety
    /// `ptr..ptr+len` must be readable for `'a`.
    #[inline]
    pub unsafe fn as_str<'a>(self) -> Option<&'a str> {
        // SAFETY: forwarded to the caller.
        utf8(unsafe { self.as_bytes() })
    }
}

/// A borrowed byte buffer.
pub type BytesView = StrView;

/// Where a callee reports an error message: the caller owns `ctx` and copies the text.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct ErrorSink {
    /// The caller's context.
    pub ctx: *mut c_void,
    /// Called at most once with a borrowed message.
    pub set: unsafe extern "C" fn(ctx: *mut c_void, message: StrView),
}

thread_local! {
    /// Where the executor factory or the backend `init` running on this thread hands back
    /// its options as it read them (ABI 1.8), if its host takes them.
    static OPTIONS_OUT: std::cell::Cell<Option<ErrorSink>> = const { std::cell::Cell::new(None) };
}

/// Runs `f` (an executor factory, a backend's `init`) with `sink` as the place its
/// options are reported to.
pub(crate) fn with_options_out<R>(sink: Option<ErrorSink>, f: impl FnOnce() -> R) -> R {
    let before = OPTIONS_OUT.replace(sink);
    let out = f();
    OPTIONS_OUT.set(before);
    out
}

/// Hands `options`, as JSON, to the host of the factory or `init` running on this thread;
/// `false` when none takes them (an older host, or not called from within one) or they
/// cannot be written as JSON (a debugging aid: the dump keeps them as written).
pub(crate) fn report_options<T: serde::Serialize>(options: &T) -> bool {
    let Some(sink) = OPTIONS_OUT.get() else {
        return false;
    };
    let Ok(json) = serde_json::to_string(options) else {
        return false;
    };
    // SAFETY: the sink is live for the duration of the call this runs in
    // (`with_options_out`); the view outlives the call.
    unsafe { (sink.set)(sink.ctx, StrView::new(&json)) };
    true
}

/// Runs a backend's `init` (`f`); what it returned, and the options it reported as it read
/// them.
pub(crate) fn init_reporting<R>(f: impl FnOnce() -> R) -> (R, Option<String>) {
    let mut slot = ErrorSlot::default();
    let out = with_options_out(Some(slot.sink()), f);
    (out, slot.taken())
}

/// Writes `reported` (a backend's options as its `init` read them) to `out`.
pub(crate) fn hand_back(reported: &std::sync::Mutex<Option<String>>, out: ErrorSink) {
    let text = reported.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(json) = text.as_deref() {
        out.report(json);
    }
}

/// The `retain` entry of a table whose objects are `Arc<T>` raw pointers.
///
/// # Safety
/// `obj` is a live `Arc<T>` pointer.
pub(crate) unsafe extern "C" fn arc_retain<T>(obj: *const c_void) {
    // SAFETY: per the contract.
    unsafe { std::sync::Arc::increment_strong_count(obj.cast::<T>()) }
}

/// The `release` entry of a table whose objects are `Arc<T>` raw pointers; a panic in the
/// object's drop stays on this side.
///
/// # Safety
/// `obj` is a live `Arc<T>` pointer whose reference the caller gives up.
pub(crate) unsafe extern "C" fn arc_release<T>(obj: *const c_void) {
    // SAFETY: per the contract.
    let t = unsafe { std::sync::Arc::from_raw(obj.cast::<T>()) };
    let _ = contain(move || drop(t));
}

/// The status of a host call run under [`contain`]: OK, or `INVALID` with why (its error
/// or its panic) reported to `err`.
pub(crate) fn invalid_unless_ok(r: Result<Result<(), String>, String>, err: ErrorSink) -> Status {
    match r {
        Ok(Ok(())) => Status::OK,
        Ok(Err(why)) | Err(why) => {
            err.report(&why);
            Status::INVALID
        }
    }
}

/// Collects an error message handed back through an [`ErrorSink`].
#[derive(Debug, Default)]
pub(crate) struct ErrorSlot {
    message: Option<String>,
}

impl ErrorSlot {
    pub(crate) fn sink(&mut self) -> ErrorSink {
        unsafe extern "C" fn set(ctx: *mut c_void, message: StrView) {
            // SAFETY: `ctx` is the `&mut ErrorSlot` of `sink()`, alive for the call it was
            // passed to; the message view is valid for the duration of this call.
            let slot = unsafe { &mut *ctx.cast::<ErrorSlot>() };
            // SAFETY: the callee passes a view valid for this call.
            slot.message = Some(unsafe { message.to_string_lossy() });
        }
        ErrorSink {
            ctx: (self as *mut ErrorSlot).cast(),
            set,
        }
    }

    /// The text handed back, if any.
    pub(crate) fn taken(&mut self) -> Option<String> {
        self.message.take()
    }

    pub(crate) fn take(&mut self, fallback: impl FnOnce() -> String) -> String {
        self.message.take().unwrap_or_else(fallback)
    }

    /// `Ok` for an OK status, else the reported message (or the status number).
    pub(crate) fn result(&mut self, status: Status) -> Result<(), String> {
        if status.is_ok() {
            Ok(())
        } else {
            Err(self.take(|| format!("returned {status}")))
        }
    }
}

impl ErrorSink {
    /// Reports `message` to the caller.
    pub(crate) fn report(self, message: &str) {
        // SAFETY: an `ErrorSink` is only ever built by `ErrorSlot::sink` (ours) or by a
        // foreign caller honouring the same contract: `set` accepts a view valid for the call.
        unsafe { (self.set)(self.ctx, StrView::new(message)) }
    }
}

/// Copies `s` into a NUL-padded array at compile time (truncating if too long).
pub const fn padded<const N: usize>(s: &str) -> [u8; N] {
    let bytes = s.as_bytes();
    let mut out = [0u8; N];
    let mut i = 0;
    while i < bytes.len() && i < N - 1 {
        out[i] = bytes[i];
        i += 1;
    }
    out
}

/// `bytes` as text: borrowed when they are valid UTF-8, else a copy with each invalid
/// sequence replaced by U+FFFD — what [`String::from_utf8_lossy`] gives. From 16 bytes
/// on, the valid case (nearly every header, meta value and message) takes
/// `str::from_utf8`'s word-at-a-time path, several times cheaper than the lossy scan's
/// byte loop; below that the byte loop is cheaper than `from_utf8`'s set-up.
///
/// ```
/// use aimrt_plugin_api::ffi::lossy;
/// assert_eq!(lossy(b"aimrt-backend"), "aimrt-backend");
/// assert_eq!(lossy(b"bad \xff byte"), "bad \u{fffd} byte");
/// assert_eq!(lossy(b"a longer text with a bad \xff byte"), "a longer text with a bad \u{fffd} byte");
/// ```
pub fn lossy(bytes: &[u8]) -> std::borrow::Cow<'_, str> {
    if bytes.len() < 16 {
        return String::from_utf8_lossy(bytes);
    }
    match std::str::from_utf8(bytes) {
        Ok(text) => std::borrow::Cow::Borrowed(text),
        Err(_) => String::from_utf8_lossy(bytes),
    }
}

/// `bytes` as text, if they are UTF-8. ASCII (AimRT's keys, format names and numbers) is
/// told by `is_ascii`, which costs a fraction of `str::from_utf8` on the short fields read
/// per message (callgrind: about 10 instructions against 48 for `pb`); other text goes
/// through `str::from_utf8`.
///
/// ```
/// use aimrt_plugin_api::ffi::utf8;
/// assert_eq!(utf8(b"pb"), Some("pb"));
/// assert_eq!(utf8("clé".as_bytes()), Some("clé"));
/// assert_eq!(utf8(b"bad \xff byte"), None);
/// ```
#[inline]
pub fn utf8(bytes: &[u8]) -> Option<&str> {
    ascii(bytes).or_else(|| std::str::from_utf8(bytes).ok())
}

/// `bytes` as text if every byte is ASCII; `None` for any other bytes, UTF-8 or not.
///
/// ```
/// use aimrt_plugin_api::ffi::ascii;
/// assert_eq!(ascii(b"aimrt-pub_seq"), Some("aimrt-pub_seq"));
/// assert_eq!(ascii("clé".as_bytes()), None);
/// ```
#[inline]
pub fn ascii(bytes: &[u8]) -> Option<&str> {
    // SAFETY: ASCII bytes are UTF-8.
    bytes
        .is_ascii()
        .then(|| unsafe { std::str::from_utf8_unchecked(bytes) })
}

/// Reads a NUL-padded array written by [`padded`].
pub fn unpad(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

/// Runs `f`, containing a panic: `Err(message)` instead of unwinding across `extern "C"`.
pub(crate) fn contain<R>(f: impl FnOnce() -> R) -> Result<R, String> {
    crate::panic::contain(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_records_size_and_minor() {
        let h = Header::of::<ExecutorVtable>();
        assert_eq!(h.size as usize, size_of::<ExecutorVtable>());
        assert_eq!(h.abi_minor, ABI_MINOR);
        assert!(h.has(size_of::<ExecutorVtable>()));
        assert!(!h.has(size_of::<ExecutorVtable>() + 1));
    }

    #[test]
    fn layout_of_the_basic_types_is_fixed() {
        assert_eq!(size_of::<Header>(), 8);
        assert_eq!(size_of::<Status>(), 4);
        assert_eq!(size_of::<StrView>(), 2 * size_of::<usize>());
        assert_eq!(align_of::<StrView>(), align_of::<usize>());
        assert_eq!(size_of::<ErrorSink>(), 2 * size_of::<usize>());
        assert_eq!(MAGIC.to_le_bytes(), *b"AIMRTRS\0");
    }

    #[test]
    fn padded_round_trips_and_truncates() {
        let p: [u8; 8] = padded("abc");
        assert_eq!(unpad(&p), "abc");
        let t: [u8; 4] = padded("abcdef");
        assert_eq!(unpad(&t), "abc");
    }

    #[test]
    fn error_slot_collects_message() {
        let mut slot = ErrorSlot::default();
        slot.sink().report("bad option 'x'");
        assert_eq!(slot.take(|| "none".into()), "bad option 'x'");
        assert_eq!(slot.take(|| "none".into()), "none");
    }
}
