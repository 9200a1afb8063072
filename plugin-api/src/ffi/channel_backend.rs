//! Channel backends across the ABI (plugin → host), their exporter and importer.
//!
//! The built-in `local` backend goes through this same table, so a backend from a plugin
//! needs nothing the runtime does not already do for `local`.

use std::ffi::c_void;

use super::channel::TypeSupportVtable;
use super::pubsub::{RawPublication, RawSink};
use super::rpc::report;
use super::{contain, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::channel::{ChannelBackend, Publication, PublisherInfo, Sink, Subscription};
use crate::BackendOptions;

/// A channel backend contributed by a plugin (or the built-in `local`).
#[repr(C)]
pub struct RawChannelBackend {
    /// The operations.
    pub vtable: *const ChannelBackendVtable,
    /// The plugin's object.
    pub obj: *const c_void,
}

// SAFETY: backend objects are `Send + Sync` (required by the exporter).
unsafe impl Send for RawChannelBackend {}
// SAFETY: see `Send`.
unsafe impl Sync for RawChannelBackend {}

/// Channel backend operations. The message-carrying entries came with ABI 1.1; the host
/// refuses a table without them.
#[repr(C)]
pub struct ChannelBackendVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The backend type the config names (`backends: [{type: local}]`).
    pub type_name: unsafe extern "C" fn(obj: *const c_void) -> StrView,
    /// Reads its options.
    pub init: unsafe extern "C" fn(
        obj: *const c_void,
        options_json: StrView,
        location: StrView,
        err: ErrorSink,
    ) -> Status,
    /// Starts delivering.
    pub start: unsafe extern "C" fn(obj: *const c_void, err: ErrorSink) -> Status,
    /// Stops delivering.
    pub shutdown: unsafe extern "C" fn(obj: *const c_void),
    /// Frees the backend.
    pub drop: unsafe extern "C" fn(obj: *const c_void),
    /// A module publishes messages of `ts` on `topic` (ABI 1.1).
    pub register_publish_type: unsafe extern "C" fn(
        obj: *const c_void,
        topic: StrView,
        ts: *const TypeSupportVtable,
        pkg: StrView,
        module: StrView,
        err: ErrorSink,
    ) -> Status,
    /// A module subscribes to `topic`; the backend takes over `sink` (also on failure)
    /// (ABI 1.1).
    pub subscribe: unsafe extern "C" fn(
        obj: *const c_void,
        topic: StrView,
        pkg: StrView,
        module: StrView,
        sink: RawSink,
        err: ErrorSink,
    ) -> Status,
    /// Carries one message; writes how many subscriptions it reached (`u64::MAX`: cannot
    /// tell) (ABI 1.1).
    pub publish: unsafe extern "C" fn(
        obj: *const c_void,
        publication: *const RawPublication,
        receivers: *mut u64,
        err: ErrorSink,
    ) -> Status,
    /// Writes to `out` the options as `init` read them, defaults filled in (JSON), if the
    /// backend reported them (ABI 1.8; `--dump_cfg_file`).
    pub reported_options: unsafe extern "C" fn(obj: *const c_void, out: ErrorSink),
}

struct BackendObj<B> {
    type_name: String,
    backend: B,
    /// The options `init` reported as it read them.
    reported: std::sync::Mutex<Option<String>>,
}

impl<B: ChannelBackend> BackendObj<B> {
    const VTABLE: ChannelBackendVtable = ChannelBackendVtable {
        header: Header::of::<ChannelBackendVtable>(),
        type_name: Self::type_name,
        init: Self::init,
        start: Self::start,
        shutdown: Self::shutdown,
        drop: Self::drop,
        register_publish_type: Self::register_publish_type,
        subscribe: Self::subscribe,
        publish: Self::publish,
        reported_options: Self::reported_options,
    };

    /// # Safety
    /// `obj` comes from `RawChannelBackend::new::<B>` and was not dropped.
    unsafe fn get<'a>(obj: *const c_void) -> &'a BackendObj<B> {
        // SAFETY: per the contract.
        unsafe { &*obj.cast::<BackendObj<B>>() }
    }

    unsafe extern "C" fn type_name(obj: *const c_void) -> StrView {
        // SAFETY: live object (vtable contract).
        StrView::new(&unsafe { Self::get(obj) }.type_name)
    }

    unsafe extern "C" fn init(
        obj: *const c_void,
        options_json: StrView,
        location: StrView,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live object; views valid for this call.
        let (this, options) = unsafe {
            let this = Self::get(obj);
            let options = BackendOptions::new(
                format!("channel backend '{}'", this.type_name),
                options_json.to_string_lossy(),
                location.to_string_lossy(),
            );
            (this, options)
        };
        let (result, reported) = super::init_reporting(|| contain(|| this.backend.init(&options)));
        *this.reported.lock().unwrap_or_else(|e| e.into_inner()) = reported;
        report(err, result)
    }

    unsafe extern "C" fn reported_options(obj: *const c_void, out: ErrorSink) {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        super::hand_back(&this.reported, out);
    }

    unsafe extern "C" fn start(obj: *const c_void, err: ErrorSink) -> Status {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        report(err, contain(|| this.backend.start()))
    }

    unsafe extern "C" fn shutdown(obj: *const c_void) {
        // SAFETY: live object.
        let this = unsafe { Self::get(obj) };
        if let Err(panic) = contain(|| this.backend.shutdown()) {
            tracing::error!(target: "aimrt", "channel backend '{}' panicked in shutdown: {panic}", this.type_name);
        }
    }

    unsafe extern "C" fn drop(obj: *const c_void) {
        // SAFETY: called once, last; the pointer came from `Box::into_raw`.
        let b = unsafe { Box::from_raw(obj.cast_mut().cast::<BackendObj<B>>()) };
        let _ = contain(move || std::mem::drop(b));
    }

    unsafe extern "C" fn register_publish_type(
        obj: *const c_void,
        topic: StrView,
        ts: *const TypeSupportVtable,
        pkg: StrView,
        module: StrView,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live object; the views are valid for this call; tables are static data
        // of never-unloaded libraries.
        let (this, info) = unsafe {
            (
                Self::get(obj),
                PublisherInfo {
                    topic: topic.as_str().unwrap_or(""),
                    type_support: &*ts,
                    pkg: pkg.as_str().unwrap_or(""),
                    module: module.as_str().unwrap_or(""),
                },
            )
        };
        report(err, contain(|| this.backend.register_publish_type(&info)))
    }

    unsafe extern "C" fn subscribe(
        obj: *const c_void,
        topic: StrView,
        pkg: StrView,
        module: StrView,
        sink: RawSink,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live object; the views are valid for this call.
        let (this, subscription) = unsafe {
            (
                Self::get(obj),
                Subscription {
                    topic: topic.to_string_lossy(),
                    pkg: pkg.to_string_lossy(),
                    module: module.to_string_lossy(),
                    sink: Sink::from_raw(sink),
                },
            )
        };
        report(err, contain(move || this.backend.subscribe(subscription)))
    }

    unsafe extern "C" fn publish(
        obj: *const c_void,
        publication: *const RawPublication,
        receivers: *mut u64,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: live object; the publication is valid for this call (vtable contract).
        let (this, publication) = unsafe { (Self::get(obj), Publication::new(&*publication)) };
        let result = contain(|| {
            this.backend.publish(&publication).map(|n| {
                // SAFETY: `receivers` is writable (vtable contract).
                unsafe { receivers.write(n) }
            })
        });
        report(err, result)
    }
}

impl RawChannelBackend {
    /// Exports `backend`.
    pub fn new<B: ChannelBackend>(backend: B) -> RawChannelBackend {
        let obj = Box::new(BackendObj {
            type_name: backend.type_name().to_owned(),
            backend,
            reported: Default::default(),
        });
        RawChannelBackend {
            vtable: &BackendObj::<B>::VTABLE,
            obj: Box::into_raw(obj).cast_const().cast(),
        }
    }

    fn vt(&self) -> &ChannelBackendVtable {
        // SAFETY: the vtable is `'static` (its library is never unloaded).
        unsafe { &*self.vtable }
    }

    /// The backend type (host use).
    pub fn type_name(&self) -> String {
        // SAFETY: live object; view copied at once.
        unsafe { (self.vt().type_name)(self.obj).to_string_lossy() }
    }

    /// Whether its table has every entry of this ABI (host use): a table from ABI 1.0
    /// cannot carry messages.
    pub fn is_complete(&self) -> bool {
        let h = self.vt().header;
        // `publish`, the last 1.1 entry, ends where 1.8's first begins.
        h.abi_minor >= 1 && h.has(std::mem::offset_of!(ChannelBackendVtable, reported_options))
    }

    /// The options as the backend's `init` read them (JSON), if it reported them (host use;
    /// a table older than 1.8 has no entry for it).
    pub fn reported_options(&self) -> Option<String> {
        if !self.vt().header.has(size_of::<ChannelBackendVtable>()) {
            return None;
        }
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; the sink outlives the call.
        unsafe { (self.vt().reported_options)(self.obj, slot.sink()) };
        slot.taken()
    }

    /// Hands the backend its options (host use).
    pub fn init(&self, options_json: &str, location: &str) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; views and the sink outlive the call.
        let status = unsafe {
            (self.vt().init)(
                self.obj,
                StrView::new(options_json),
                StrView::new(location),
                slot.sink(),
            )
        };
        slot.result(status)
    }

    /// Starts delivering (host use).
    pub fn start(&self) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: live object; the sink outlives the call.
        let status = unsafe { (self.vt().start)(self.obj, slot.sink()) };
        slot.result(status)
    }

    /// Stops delivering (host use).
    pub fn shutdown(&self) {
        // SAFETY: live object.
        unsafe { (self.vt().shutdown)(self.obj) }
    }

    /// Tells the backend about a publish type (host use; needs [`is_complete`](Self::is_complete)).
    pub fn register_publish_type(&self, info: &PublisherInfo<'_>) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        // SAFETY: a complete, live table; views and the sink outlive the call.
        let status = unsafe {
            (self.vt().register_publish_type)(
                self.obj,
                StrView::new(info.topic),
                info.type_support,
                StrView::new(info.pkg),
                StrView::new(info.module),
                slot.sink(),
            )
        };
        slot.result(status)
    }

    /// Hands the backend a subscription (host use; needs [`is_complete`](Self::is_complete)).
    pub fn subscribe(
        &self,
        topic: &str,
        pkg: &str,
        module: &str,
        sink: RawSink,
    ) -> Result<(), String> {
        let mut slot = ErrorSlot::default();
        let sink = std::mem::ManuallyDrop::new(sink);
        // SAFETY: a complete, live table; the sink's reference passes to the backend.
        let status = unsafe {
            (self.vt().subscribe)(
                self.obj,
                StrView::new(topic),
                StrView::new(pkg),
                StrView::new(module),
                std::ptr::read(&*sink),
                slot.sink(),
            )
        };
        slot.result(status)
    }

    /// Carries one message; the number of subscriptions reached (host use).
    pub fn publish(&self, publication: &RawPublication) -> Result<u64, String> {
        let mut slot = ErrorSlot::default();
        let mut receivers = crate::channel::RECEIVERS_UNKNOWN;
        // SAFETY: a complete, live table; the publication, `receivers` and the sink
        // outlive the call.
        let status =
            unsafe { (self.vt().publish)(self.obj, publication, &mut receivers, slot.sink()) };
        slot.result(status).map(|()| receivers)
    }
}

impl Drop for RawChannelBackend {
    fn drop(&mut self) {
        // SAFETY: we own the object; `drop` is its last use.
        unsafe { (self.vt().drop)(self.obj) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::channel::{PublisherInfo, Subscription};
    use crate::Error;

    #[derive(serde::Deserialize, serde::Serialize)]
    #[serde(deny_unknown_fields)]
    struct Opts {
        #[serde(default = "yes")]
        inline: bool,
    }

    fn yes() -> bool {
        true
    }

    /// A backend that reads [`Opts`], reporting them when `report`.
    struct Reads {
        report: bool,
    }

    impl ChannelBackend for Reads {
        fn type_name(&self) -> &str {
            "reads"
        }
        fn init(&self, options: &BackendOptions) -> Result<(), Error> {
            let o: Opts = if self.report {
                options.read()?
            } else {
                options.get()?
            };
            assert!(o.inline);
            Ok(())
        }
        fn register_publish_type(&self, _: &PublisherInfo<'_>) -> Result<(), Error> {
            Ok(())
        }
        fn subscribe(&self, _: Subscription) -> Result<(), Error> {
            Ok(())
        }
        fn publish(&self, _: &Publication<'_>) -> Result<u64, Error> {
            Ok(0)
        }
    }

    #[test]
    fn a_backend_reports_its_options_as_read_and_a_table_of_1_7_is_complete_without_them() {
        let raw = RawChannelBackend::new(Reads { report: true });
        assert_eq!(raw.reported_options(), None, "nothing before init");
        raw.init("null", "cfg.yaml:3:9").unwrap();
        assert_eq!(
            raw.reported_options().as_deref(),
            Some(r#"{"inline":true}"#)
        );
        let quiet = RawChannelBackend::new(Reads { report: false });
        quiet.init("null", "cfg.yaml:3:9").unwrap();
        assert_eq!(quiet.reported_options(), None);

        // A table of 1.7 ends with `publish`: it carries messages, and reports nothing.
        static TABLE_1_7: ChannelBackendVtable = ChannelBackendVtable {
            header: Header {
                size: std::mem::offset_of!(ChannelBackendVtable, reported_options) as u32,
                abi_minor: 7,
            },
            ..BackendObj::<Reads>::VTABLE
        };
        let old = RawChannelBackend {
            vtable: &TABLE_1_7,
            obj: raw.obj,
        };
        assert!(old.is_complete());
        assert_eq!(old.reported_options(), None);
        std::mem::forget(old);
    }
}
