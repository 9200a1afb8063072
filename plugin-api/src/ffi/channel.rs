//! Message type support across the ABI (DESIGN §6): one `#[repr(C)]` table per message type
//! per library, and a reference-counted message object that only its own library's code
//! touches.
//!
//! A message object is an `Arc<M>` turned into a raw pointer by the library that owns `M`'s
//! table. Another library can encode it, share it (one more reference) or drop its
//! reference, always through that table. Two libraries exchange a message by encoding it
//! once per format and decoding it with the receiver's table; within one library the same
//! object is shared. "Same library and type" means the same table (pointer equality),
//! never `TypeId`.

use std::ffi::c_void;
use std::marker::PhantomData;
use std::sync::Arc;

use super::{contain, BytesView, ErrorSink, ErrorSlot, Header, Status, StrView};
use crate::channel::Message;

/// The operations on one message type, in the library that defines it.
#[repr(C)]
pub struct TypeSupportVtable {
    /// Size and minor of this table.
    pub header: Header,
    /// The type name (`serde:…`, `pb:…`); static.
    pub type_name: unsafe extern "C" fn() -> StrView,
    /// Number of formats.
    pub format_count: unsafe extern "C" fn() -> usize,
    /// The `index`-th format (0 is the default); static.
    pub format: unsafe extern "C" fn(index: usize) -> StrView,
    /// Encodes `msg` (an object of this table) in `format`; hands the bytes to `out`.
    pub encode: unsafe extern "C" fn(
        msg: *const c_void,
        format: StrView,
        out: BytesSink,
        err: ErrorSink,
    ) -> Status,
    /// Decodes a new object (one reference) from `bytes` in `format` into `out`.
    pub decode: unsafe extern "C" fn(
        format: StrView,
        bytes: BytesView,
        out: *mut *const c_void,
        err: ErrorSink,
    ) -> Status,
    /// Adds a reference to `msg`.
    pub retain: unsafe extern "C" fn(msg: *const c_void),
    /// Drops a reference to `msg` (the last one frees it).
    pub release: unsafe extern "C" fn(msg: *const c_void),
    /// (1.3) The type's schema for recordings: its encoding (`protobuf`, `jsonschema`, or
    /// empty for none), name and bytes, all static.
    pub schema:
        unsafe extern "C" fn(encoding: *mut StrView, name: *mut StrView, data: *mut BytesView),
}

/// A type's schema as a table of any minor describes it (`None`: a table older than 1.3,
/// or a type without one).
pub fn schema_of(
    ts: &'static TypeSupportVtable,
) -> Option<(&'static str, &'static str, &'static [u8])> {
    if !ts.header.has(size_of::<TypeSupportVtable>()) {
        return None;
    }
    let (mut encoding, mut name) = (StrView::EMPTY, StrView::EMPTY);
    let mut data = BytesView {
        ptr: std::ptr::null(),
        len: 0,
    };
    // SAFETY: the table has the entry (size checked); it writes views of static data.
    unsafe { (ts.schema)(&mut encoding, &mut name, &mut data) };
    // SAFETY: the views are of static data of a never-unloaded library.
    let (encoding, name, data) = unsafe {
        (
            encoding.as_str().unwrap_or(""),
            name.as_str().unwrap_or(""),
            data.as_bytes(),
        )
    };
    (!encoding.is_empty()).then_some((encoding, name, data))
}

impl std::fmt::Debug for TypeSupportVtable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TypeSupportVtable")
            // SAFETY: tables are static; the view is copied at once.
            .field("type_name", &unsafe {
                (self.type_name)().to_string_lossy()
            })
            .finish()
    }
}

/// Where a callee hands over bytes: the caller copies them during the call.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct BytesSink {
    /// The caller's context.
    pub ctx: *mut c_void,
    /// Called at most once with borrowed bytes.
    pub set: unsafe extern "C" fn(ctx: *mut c_void, bytes: BytesView),
}

struct Ts<M>(PhantomData<M>);

impl<M: Message> Ts<M> {
    const VTABLE: TypeSupportVtable = TypeSupportVtable {
        header: Header::of::<TypeSupportVtable>(),
        type_name: Self::type_name,
        format_count: Self::format_count,
        format: Self::format,
        encode: Self::encode,
        decode: Self::decode,
        retain: Self::retain,
        release: Self::release,
        schema: Self::schema,
    };

    unsafe extern "C" fn schema(encoding: *mut StrView, name: *mut StrView, data: *mut BytesView) {
        let s = M::schema();
        // SAFETY: the caller passes writable slots; the views are of static data.
        unsafe {
            *encoding = StrView::new(s.encoding);
            *name = StrView::new(s.name);
            *data = bytes_view(s.data);
        }
    }

    unsafe extern "C" fn type_name() -> StrView {
        StrView::new(M::type_name())
    }

    unsafe extern "C" fn format_count() -> usize {
        M::formats().len()
    }

    unsafe extern "C" fn format(index: usize) -> StrView {
        M::formats()
            .get(index)
            .map_or(StrView::EMPTY, |f| StrView::new(f))
    }

    unsafe extern "C" fn encode(
        msg: *const c_void,
        format: StrView,
        out: BytesSink,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: `msg` is a live `Arc<M>` pointer of this table (vtable contract).
        let m = unsafe { &*msg.cast::<M>() };
        // SAFETY: the view is valid for this call.
        let format = unsafe { format.to_str_lossy() };
        match contain(|| m.encode(&format)) {
            Ok(Ok(bytes)) => {
                // SAFETY: the caller's sink accepts a view valid for this call.
                unsafe { (out.set)(out.ctx, bytes_view(&bytes)) };
                Status::OK
            }
            Ok(Err(e)) => {
                err.report(&e.to_string());
                Status::INVALID
            }
            Err(panic) => {
                err.report(&format!("encoding panicked: {panic}"));
                Status::FAILED
            }
        }
    }

    unsafe extern "C" fn decode(
        format: StrView,
        bytes: BytesView,
        out: *mut *const c_void,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: the views are valid for this call.
        let (format, bytes) = unsafe { (format.to_str_lossy(), bytes.as_bytes()) };
        match contain(|| M::decode(&format, bytes)) {
            Ok(Ok(m)) => {
                // SAFETY: `out` is writable (vtable contract).
                unsafe { out.write(Arc::into_raw(Arc::new(m)).cast()) };
                Status::OK
            }
            Ok(Err(e)) => {
                err.report(&e.to_string());
                Status::INVALID
            }
            Err(panic) => {
                err.report(&format!("decoding panicked: {panic}"));
                Status::FAILED
            }
        }
    }

    unsafe extern "C" fn retain(msg: *const c_void) {
        // SAFETY: a live `Arc<M>` pointer of this table.
        unsafe { Arc::increment_strong_count(msg.cast::<M>()) };
    }

    unsafe extern "C" fn release(msg: *const c_void) {
        // SAFETY: a live `Arc<M>` pointer of this table; the caller gives up one reference.
        let m = unsafe { Arc::from_raw(msg.cast::<M>()) };
        let _ = contain(move || drop(m));
    }
}

fn bytes_view(bytes: &[u8]) -> BytesView {
    StrView {
        ptr: bytes.as_ptr(),
        len: bytes.len(),
    }
}

/// The type-support table of `M` in this library.
pub fn type_support<M: Message>() -> &'static TypeSupportVtable {
    &Ts::<M>::VTABLE
}

/// One reference to a message object, with the table of the library that owns it.
pub struct RawMessage {
    ts: &'static TypeSupportVtable,
    ptr: *const c_void,
}

// SAFETY: message objects are `Send + Sync` (`Message` requires both) and only touched
// through their own table.
unsafe impl Send for RawMessage {}
// SAFETY: see `Send`.
unsafe impl Sync for RawMessage {}

impl std::fmt::Debug for RawMessage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawMessage")
            .field("type", &type_name_of(self.ts))
            .finish()
    }
}

/// The type name of a table (empty if it is not UTF-8).
pub fn type_name_of(ts: &'static TypeSupportVtable) -> &'static str {
    // SAFETY: tables and their type names are static data of never-unloaded libraries.
    unsafe { (ts.type_name)().as_str().unwrap_or("") }
}

/// The formats of a table, default first.
pub fn formats_of(ts: &TypeSupportVtable) -> Vec<String> {
    // SAFETY: tables are static; views are copied at once.
    unsafe {
        (0..(ts.format_count)())
            .map(|i| (ts.format)(i).to_string_lossy())
            .collect()
    }
}

impl RawMessage {
    /// Wraps a message of this library.
    pub fn new<M: Message>(msg: Arc<M>) -> RawMessage {
        RawMessage {
            ts: type_support::<M>(),
            ptr: Arc::into_raw(msg).cast(),
        }
    }

    /// Takes over one reference to `ptr`, an object of `ts`.
    ///
    /// # Safety
    /// `ptr` must be a live object of `ts` whose reference the caller gives up.
    pub unsafe fn from_raw(ts: &'static TypeSupportVtable, ptr: *const c_void) -> RawMessage {
        RawMessage { ts, ptr }
    }

    /// Gives up ownership without releasing: `(table, object)`.
    pub fn into_raw(self) -> (&'static TypeSupportVtable, *const c_void) {
        let me = std::mem::ManuallyDrop::new(self);
        (me.ts, me.ptr)
    }

    /// Its table.
    pub fn type_support(&self) -> &'static TypeSupportVtable {
        self.ts
    }

    /// The object pointer (still owned by `self`).
    pub fn as_ptr(&self) -> *const c_void {
        self.ptr
    }

    /// One more reference to the same object.
    pub fn share(&self) -> RawMessage {
        // SAFETY: a live object of its own table.
        unsafe { (self.ts.retain)(self.ptr) };
        RawMessage {
            ts: self.ts,
            ptr: self.ptr,
        }
    }

    /// Encodes it in `format`.
    pub fn encode(&self, format: &str) -> Result<Vec<u8>, String> {
        let mut out = Vec::new();
        self.encode_into(format, &mut out).map(|()| out)
    }

    /// Encodes the object in `format`, appending the bytes to `out` (e.g. behind a
    /// header already written there); on failure `out` is as it was.
    pub fn encode_into(&self, format: &str, out: &mut Vec<u8>) -> Result<(), String> {
        self.encode_with(format, |bytes| out.extend_from_slice(bytes))
    }

    /// Encodes the object in `format` and hands the bytes, borrowed, to `then`, which
    /// puts them where they go (one copy: e.g. straight into a shared-memory buffer);
    /// `Err` says why it cannot be encoded, and `then` is not called.
    ///
    /// ```
    /// use std::sync::Arc;
    /// use aimrt_plugin_api::ffi::RawMessage;
    /// #[derive(serde::Serialize, serde::Deserialize)]
    /// struct Pose { x: f64 }
    /// aimrt_plugin_api::serde_message!(Pose, "example.Pose");
    /// let msg = RawMessage::new(Arc::new(Pose { x: 1.5 }));
    /// let len = msg.encode_with("json", |bytes| bytes.len()).unwrap();
    /// assert_eq!(len, br#"{"x":1.5}"#.len());
    /// ```
    pub fn encode_with<R, F: FnOnce(&[u8]) -> R>(
        &self,
        format: &str,
        then: F,
    ) -> Result<R, String> {
        type Caught<R> = std::thread::Result<R>;
        struct Slot<F, R> {
            then: Option<F>,
            out: Option<Caught<R>>,
        }
        unsafe extern "C" fn set<F: FnOnce(&[u8]) -> R, R>(ctx: *mut c_void, bytes: BytesView) {
            // SAFETY: `ctx` is the `Slot` below, alive for the call; the view is valid for
            // this call.
            let (slot, bytes) = unsafe { (&mut *ctx.cast::<Slot<F, R>>(), bytes.as_bytes()) };
            if let Some(then) = slot.then.take() {
                // A panic must not unwind through the encoder: it is resumed below.
                let run = std::panic::AssertUnwindSafe(|| then(bytes));
                slot.out = Some(std::panic::catch_unwind(run));
            }
        }
        let mut slot = Slot {
            then: Some(then),
            out: None,
        };
        let sink = BytesSink {
            ctx: (&mut slot as *mut Slot<F, R>).cast(),
            set: set::<F, R>,
        };
        let mut err = ErrorSlot::default();
        // SAFETY: a live object of its own table; the sinks outlive the call.
        let status = unsafe { (self.ts.encode)(self.ptr, StrView::new(format), sink, err.sink()) };
        match (slot.out, slot.then) {
            (Some(Err(panic)), _) => std::panic::resume_unwind(panic),
            _ if !status.is_ok() => Err(err.take(|| format!("returned {status}"))),
            (Some(Ok(out)), _) => Ok(out),
            // An encoder that handed over nothing encoded to no bytes.
            (None, Some(then)) => Ok(then(&[])),
            (None, None) => Err("the encoder's sink ran but kept nothing".into()),
        }
    }

    /// Decodes a new object of `ts` from `bytes` in `format`.
    pub fn decode(
        ts: &'static TypeSupportVtable,
        format: &str,
        bytes: &[u8],
    ) -> Result<RawMessage, String> {
        let mut out: *const c_void = std::ptr::null();
        let mut slot = ErrorSlot::default();
        // SAFETY: tables are static; the views, `out` and the sink outlive the call.
        let status = unsafe {
            (ts.decode)(
                StrView::new(format),
                bytes_view(bytes),
                &mut out,
                slot.sink(),
            )
        };
        if status.is_ok() && !out.is_null() {
            Ok(RawMessage { ts, ptr: out })
        } else {
            Err(slot.take(|| format!("returned {status}")))
        }
    }

    /// The message as `Arc<M>`, if it is an object of `M`'s table in this library.
    pub fn downcast<M: Message>(self) -> Result<Arc<M>, RawMessage> {
        if std::ptr::eq(self.ts, type_support::<M>()) {
            let (_, ptr) = self.into_raw();
            // SAFETY: the same table means an `Arc<M>` made by this library's code.
            Ok(unsafe { Arc::from_raw(ptr.cast::<M>()) })
        } else {
            Err(self)
        }
    }
}

impl Drop for RawMessage {
    fn drop(&mut self) {
        // SAFETY: we own one reference to a live object of its table.
        unsafe { (self.ts.release)(self.ptr) }
    }
}

#[cfg(test)]
mod tests {
    #[derive(Debug, serde::Serialize, serde::Deserialize)]
    struct Probe {
        n: u32,
    }
    crate::serde_message!(Probe, "test.Probe");

    #[test]
    fn encoding_into_a_buffer_appends_and_a_failure_leaves_it_as_it_was() {
        let msg = RawMessage::new(std::sync::Arc::new(Probe { n: 300 }));
        let mut out = b"head".to_vec();
        msg.encode_into("json", &mut out).unwrap();
        assert_eq!(out, b"head{\"n\":300}");
        assert_eq!(&out[4..], msg.encode("json").unwrap());
        let err = msg.encode_into("xml", &mut out).unwrap_err();
        assert!(err.contains("xml"), "{err}");
        assert_eq!(out, b"head{\"n\":300}");
    }

    #[test]
    fn a_serde_type_has_a_json_schema_and_an_older_table_none() {
        let ts = type_support::<Probe>();
        let (encoding, name, data) = schema_of(ts).expect("a 1.3 table");
        assert_eq!((encoding, name), ("jsonschema", "test.Probe"));
        let schema: serde_json::Value = serde_json::from_slice(data).expect("JSON");
        assert_eq!(schema["title"], "test.Probe");
        assert_eq!(schema["type"], "object");
        // A table of 1.2 ends before `schema`: the host never reads past it.
        let old: &'static TypeSupportVtable = Box::leak(Box::new(TypeSupportVtable {
            header: Header {
                size: std::mem::offset_of!(TypeSupportVtable, schema) as u32,
                abi_minor: 2,
            },
            ..Ts::<Probe>::VTABLE
        }));
        assert_eq!(schema_of(old), None);
    }

    use super::*;

    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Hello {
        text: String,
    }
    crate::serde_message!(Hello, "test.Hello");

    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Other {
        text: String,
    }
    crate::serde_message!(Other, "test.Other");

    #[test]
    fn encode_with_hands_the_bytes_over_once_and_keeps_a_panic_on_the_callers_side() {
        let raw = RawMessage::new(Arc::new(Hello { text: "hi".into() }));
        let mut calls = 0;
        let len = raw
            .encode_with("json", |bytes| {
                calls += 1;
                assert_eq!(bytes, br#"{"text":"hi"}"#);
                bytes.len()
            })
            .unwrap();
        assert_eq!((len, calls), (13, 1));
        // A format the type lacks: an error, and the closure never runs.
        let err = raw
            .encode_with("xml", |_| panic!("not called"))
            .unwrap_err();
        assert!(err.contains("xml"), "{err}");
        // A panic in the closure does not cross the encoder's C frame: it unwinds here.
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            raw.encode_with("json", |_| -> () { panic!("from the closure") })
        }));
        let panic = caught.unwrap_err();
        assert_eq!(panic.downcast_ref::<&str>(), Some(&"from the closure"));
    }

    #[test]
    fn share_encode_decode_and_downcast() {
        let msg = Arc::new(Hello { text: "hi".into() });
        let raw = RawMessage::new(msg.clone());
        assert_eq!(type_name_of(raw.type_support()), "serde:test.Hello");
        assert_eq!(formats_of(raw.type_support()), ["postcard", "json"]);
        let shared = raw.share();
        assert_eq!(Arc::strong_count(&msg), 3);
        drop(raw);
        assert_eq!(Arc::strong_count(&msg), 2);
        let json = shared.encode("json").unwrap();
        assert_eq!(json, br#"{"text":"hi"}"#);
        assert!(shared
            .encode("pb")
            .unwrap_err()
            .contains("does not support the format 'pb'"));
        // Decoded with another table: a new object of that type.
        let other = RawMessage::decode(type_support::<Other>(), "json", &json).unwrap();
        let other = other.downcast::<Other>().unwrap();
        assert_eq!(other.text, "hi");
        // The same object comes back as the same Arc; a foreign table does not downcast.
        let back = shared.downcast::<Hello>().unwrap();
        assert!(Arc::ptr_eq(&back, &msg));
        let not = RawMessage::new(Arc::new(Other {
            text: String::new(),
        }));
        assert!(not.downcast::<Hello>().is_err());
        drop(back);
        assert_eq!(Arc::strong_count(&msg), 1);
        let e = RawMessage::decode(type_support::<Hello>(), "postcard", &[0xff]).unwrap_err();
        assert!(e.contains("cannot deserialize 'serde:test.Hello'"), "{e}");
    }
}
