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
use crate::channel::message::not_encoded;
use crate::channel::{Message, MessageError};

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
    /// (1.5) Encodes `msg` in `format` into memory the caller gives: calls `out.room`
    /// once with the exact length, then writes exactly that many bytes where it points
    /// (a null pointer: the caller refuses, and `INVALID` is returned). On an error
    /// after `room` the bytes there are unspecified.
    pub encode_to: unsafe extern "C" fn(
        msg: *const c_void,
        format: StrView,
        out: RoomSink,
        err: ErrorSink,
    ) -> Status,
}

/// Where the table's `schema` entry (1.3) ends: a table at least this long has it.
const SCHEMA_END: usize = std::mem::offset_of!(TypeSupportVtable, schema) + size_of::<usize>();
/// Where its `encode_to` entry (1.5) ends.
const ENCODE_TO_END: usize =
    std::mem::offset_of!(TypeSupportVtable, encode_to) + size_of::<usize>();

/// A type's schema as a table of any minor describes it (`None`: a table older than 1.3,
/// or a type without one).
pub fn schema_of(
    ts: &'static TypeSupportVtable,
) -> Option<(&'static str, &'static str, &'static [u8])> {
    if !ts.header.has(SCHEMA_END) {
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

/// Where a callee asks for room to write into (1.5, `encode_to`).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct RoomSink {
    /// The caller's context.
    pub ctx: *mut c_void,
    /// Called at most once: `len` writable bytes that stay valid until the callee
    /// returns, or null to refuse.
    pub room: unsafe extern "C" fn(ctx: *mut c_void, len: usize) -> *mut u8,
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
        retain: super::arc_retain::<M>,
        release: super::arc_release::<M>,
        schema: Self::schema,
        encode_to: Self::encode_to,
    };

    /// The format a caller names: one of `M`'s own when its bytes are (no UTF-8 check:
    /// the common case, once a message each way), else the text read lossily.
    ///
    /// # Safety
    /// The view must be readable for `'a`.
    unsafe fn format_named<'a>(format: StrView) -> std::borrow::Cow<'a, str> {
        // SAFETY: forwarded to the caller.
        let bytes = unsafe { format.as_bytes() };
        match M::formats().iter().find(|f| f.as_bytes() == bytes) {
            Some(own) => std::borrow::Cow::Borrowed(own),
            None => super::lossy(bytes),
        }
    }

    unsafe extern "C" fn encode_to(
        msg: *const c_void,
        format: StrView,
        out: RoomSink,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: `msg` is a live `Arc<M>` pointer of this table (vtable contract).
        let m = unsafe { &*msg.cast::<M>() };
        // SAFETY: the view is valid for this call.
        let format = unsafe { Self::format_named(format) };
        let room = |len: usize| -> Result<&mut [u8], MessageError> {
            // SAFETY: the caller's sink returns `len` writable bytes valid until we
            // return, or null.
            let ptr = unsafe { (out.room)(out.ctx, len) };
            if ptr.is_null() {
                let why = format!("the caller refused room for {len} bytes");
                return Err(not_encoded(M::type_name(), &format, why));
            }
            // SAFETY: as above; nothing else refers to those bytes during the call.
            Ok(unsafe { std::slice::from_raw_parts_mut(ptr, len) })
        };
        encoded(
            contain(|| match m.encoded_len(&format) {
                Some(len) => m.encode_to_slice(&format, room(len)?),
                None => {
                    let bytes = m.encode(&format)?;
                    room(bytes.len())?.copy_from_slice(&bytes);
                    Ok(())
                }
            }),
            err,
        )
    }

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
        let format = unsafe { Self::format_named(format) };
        let run = || {
            let bytes = m.encode(&format)?;
            // SAFETY: the caller's sink accepts a view valid for this call.
            unsafe { (out.set)(out.ctx, bytes_view(&bytes)) };
            Ok(())
        };
        encoded(contain(run), err)
    }

    unsafe extern "C" fn decode(
        format: StrView,
        bytes: BytesView,
        out: *mut *const c_void,
        err: ErrorSink,
    ) -> Status {
        // SAFETY: the views are valid for this call.
        let (format, bytes) = unsafe { (Self::format_named(format), bytes.as_bytes()) };
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
}

/// The status of an encoding run under [`contain`]: `OK`, `INVALID` with why it cannot
/// be encoded, or `FAILED` for a panic.
fn encoded(run: Result<Result<(), MessageError>, String>, err: ErrorSink) -> Status {
    match run {
        Ok(Ok(())) => Status::OK,
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

/// `room(len)`, checked to hold `len` bytes at its offset.
fn checked_room<T: AsMut<[u8]>>(
    room: impl FnOnce(usize) -> Result<(T, usize), String>,
    len: usize,
) -> Result<(T, usize), String> {
    let (mut buf, at) = room(len)?;
    let size = buf.as_mut().len();
    if at.checked_add(len).is_none_or(|end| end > size) {
        return Err(format!(
            "the room given ({size} bytes, the message at {at}) cannot hold {len} bytes"
        ));
    }
    Ok((buf, at))
}

fn bytes_view(bytes: &[u8]) -> BytesView {
    StrView {
        ptr: bytes.as_ptr(),
        len: bytes.len(),
    }
}

/// The type-support table of `M` in this library: for a type of the message macros, one
/// `static` of the library (one address, wherever it is asked for).
pub fn type_support<M: Message>() -> &'static TypeSupportVtable {
    M::__type_support()
}

/// `msg` under a copy of its table at another address: what the compiler may make of a
/// constant table in another code unit (tests of lookups by table; the copy is leaked).
pub fn with_copied_table(msg: RawMessage) -> RawMessage {
    let ts: &'static TypeSupportVtable = Box::leak(Box::new(TypeSupportVtable {
        header: msg.ts.header,
        ..*msg.ts
    }));
    let (_, ptr) = msg.into_raw();
    // The copy has the same functions: `ptr` is an object of it as of the original.
    RawMessage { ts, ptr }
}

/// `M`'s table as a value: what the message macros put in their `static`, and the default
/// of [`Message::__type_support`] (a constant, which the compiler may copy per code unit).
pub const fn table_of<M: Message>() -> TypeSupportVtable {
    Ts::<M>::VTABLE
}

/// `M`'s table as a library of ABI 1.4 has it: its header ends before `encode_to`, and
/// the entry there (which a host must never read) logs an error and fails.
struct Ts14<M>(PhantomData<M>);

impl<M: Message> Ts14<M> {
    const VTABLE: TypeSupportVtable = TypeSupportVtable {
        header: Header {
            size: std::mem::offset_of!(TypeSupportVtable, encode_to) as u32,
            abi_minor: 4,
        },
        encode_to: Self::past_the_table,
        ..Ts::<M>::VTABLE
    };

    unsafe extern "C" fn past_the_table(
        _: *const c_void,
        _: StrView,
        _: RoomSink,
        err: ErrorSink,
    ) -> Status {
        tracing::error!(
            "ABI 1.4 table of '{}': encode_to reached through a table that lacks it",
            M::type_name()
        );
        err.report("encode_to is not in a 1.4 table");
        Status::FAILED
    }
}

/// [`type_support`] in the 1.4 layout (`__export_type_support_as_1_4!`, for fixtures).
#[doc(hidden)]
pub fn type_support_as_1_4<M: Message>() -> &'static TypeSupportVtable {
    &Ts14::<M>::VTABLE
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

/// The type name of a table as bytes, unchecked: for matching a name already known (per
/// message, where [`type_name_of`]'s UTF-8 check would cost more than the comparison).
///
/// ```
/// use aimrt_plugin_api::ffi::{type_name_bytes_of, type_name_of, type_support};
///
/// #[derive(serde::Serialize, serde::Deserialize)]
/// struct Note {
///     text: String,
/// }
/// aimrt_plugin_api::serde_message!(Note, "example.Note");
///
/// let ts = type_support::<Note>();
/// assert_eq!(type_name_bytes_of(ts), b"serde:example.Note");
/// assert_eq!(type_name_bytes_of(ts), type_name_of(ts).as_bytes());
/// ```
pub fn type_name_bytes_of(ts: &'static TypeSupportVtable) -> &'static [u8] {
    // SAFETY: as in `type_name_of`.
    unsafe { (ts.type_name)().as_bytes() }
}

/// The first of `items` whose table (`table_of`) is `ts`: the same table by address, else
/// one of the same type name.
///
/// A table's address is not a type's identity: the compiler may place a copy of
/// [`type_support`]'s table in each code unit that uses it (Rust promises no single
/// address for a constant), and each library has its own. The name is what AimRT
/// identifies a message type by; the address is only the fast path.
///
/// ```
/// use aimrt_plugin_api::ffi::{find_table, type_support, TypeSupportVtable};
///
/// #[derive(serde::Serialize, serde::Deserialize)]
/// struct Note {
///     text: String,
/// }
/// aimrt_plugin_api::serde_message!(Note, "example.Note");
///
/// let ts = type_support::<Note>();
/// // A second copy of the same table, at another address.
/// let copy: &'static TypeSupportVtable = Box::leak(Box::new(TypeSupportVtable { header: ts.header, ..*ts }));
/// let registered = [("other", copy)];
/// assert_eq!(find_table(&registered, ts, |r| r.1).map(|r| r.0), Some("other"));
/// ```
pub fn find_table<'a, T>(
    items: &'a [T],
    ts: &'static TypeSupportVtable,
    table_of: impl Fn(&T) -> &'static TypeSupportVtable,
) -> Option<&'a T> {
    items
        .iter()
        .find(|i| std::ptr::eq(table_of(i), ts))
        .or_else(|| {
            let name = type_name_bytes_of(ts);
            items
                .iter()
                .find(|i| type_name_bytes_of(table_of(i)) == name)
        })
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
        let at = out.len();
        let grown = self.encode_to(format, |len| {
            out.resize(at + len, 0);
            Ok((&mut *out, at))
        });
        grown.map(drop).inspect_err(|_| out.truncate(at))
    }

    /// Encodes the object in `format` straight into memory `room` gives, with no copy
    /// where the type knows its encoded length (`pb`, `postcard`): `room(len)` is called
    /// once with the exact length and returns a buffer and the offset in it where the
    /// `len` bytes go (e.g. behind a header it wrote); the buffer comes back filled.
    /// `Err` says why the message cannot be encoded, or is `room`'s own error. A table
    /// older than ABI 1.5 is encoded and copied.
    ///
    /// ```
    /// use std::sync::Arc;
    /// use aimrt_plugin_api::ffi::RawMessage;
    /// #[derive(serde::Serialize, serde::Deserialize)]
    /// struct Pose { x: f64 }
    /// aimrt_plugin_api::serde_message!(Pose, "example.Pose");
    /// let msg = RawMessage::new(Arc::new(Pose { x: 1.5 }));
    /// let framed = msg
    ///     .encode_to("json", |len| {
    ///         let mut buf = vec![0; 4 + len];
    ///         buf[..4].copy_from_slice(&(len as u32).to_be_bytes());
    ///         Ok((buf, 4))
    ///     })
    ///     .unwrap();
    /// assert_eq!(&framed[..], b"\0\0\0\x09{\"x\":1.5}");
    /// ```
    pub fn encode_to<T, F>(&self, format: &str, room: F) -> Result<T, String>
    where
        T: AsMut<[u8]>,
        F: FnOnce(usize) -> Result<(T, usize), String>,
    {
        if !self.ts.header.has(ENCODE_TO_END) {
            return self
                .encode_with(format, |bytes| {
                    let (mut buf, at) = checked_room(room, bytes.len())?;
                    buf.as_mut()[at..at + bytes.len()].copy_from_slice(bytes);
                    Ok(buf)
                })
                .and_then(|filled| filled);
        }
        type Given<T> = std::thread::Result<Result<(T, usize), String>>;
        struct Slot<F, T> {
            room: Option<F>,
            given: Option<Given<T>>,
        }
        unsafe extern "C" fn give<F, T>(ctx: *mut c_void, len: usize) -> *mut u8
        where
            F: FnOnce(usize) -> Result<(T, usize), String>,
            T: AsMut<[u8]>,
        {
            // SAFETY: `ctx` is the `Slot` below, alive for the call.
            let slot = unsafe { &mut *ctx.cast::<Slot<F, T>>() };
            let Some(room) = slot.room.take() else {
                return std::ptr::null_mut();
            };
            // A panic must not unwind through the encoder: it is resumed below.
            let run = std::panic::AssertUnwindSafe(|| checked_room(room, len));
            match slot.given.insert(std::panic::catch_unwind(run)) {
                // The buffer stays in the slot, untouched, until the encoder returns.
                Ok(Ok((buf, at))) => buf.as_mut()[*at..].as_mut_ptr(),
                _ => std::ptr::null_mut(),
            }
        }
        let mut slot = Slot {
            room: Some(room),
            given: None,
        };
        let sink = RoomSink {
            ctx: (&mut slot as *mut Slot<F, T>).cast(),
            room: give::<F, T>,
        };
        let mut err = ErrorSlot::default();
        // SAFETY: a live object of its own table, whose table has `encode_to` (size
        // checked); the sinks outlive the call.
        let status =
            unsafe { (self.ts.encode_to)(self.ptr, StrView::new(format), sink, err.sink()) };
        match slot.given {
            Some(Err(panic)) => std::panic::resume_unwind(panic),
            Some(Ok(Err(refused))) => Err(refused),
            Some(Ok(Ok((buf, _)))) if status.is_ok() => Ok(buf),
            _ if !status.is_ok() => Err(err.take(|| format!("returned {status}"))),
            _ => Err("the encoder returned without asking for room".into()),
        }
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
pub(crate) mod tests {
    /// A message type for the `ffi` tests.
    #[derive(Debug, serde::Serialize, serde::Deserialize)]
    pub(crate) struct Probe {
        pub(crate) n: u32,
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
    fn encode_to_writes_into_the_callers_room_at_its_offset() {
        let raw = RawMessage::new(Arc::new(Hello { text: "hi".into() }));
        for format in ["postcard", "json"] {
            let want = raw.encode_with(format, <[u8]>::to_vec).unwrap();
            let mut asked = Vec::new();
            let buf = raw
                .encode_to(format, |len| {
                    asked.push(len);
                    Ok((vec![7u8; 3 + len + 2], 3))
                })
                .unwrap();
            assert_eq!(asked, [want.len()], "{format}: room asked once, exactly");
            assert_eq!(&buf[..3], [7; 3]);
            assert_eq!(&buf[3..3 + want.len()], want, "{format}");
            assert_eq!(&buf[3 + want.len()..], [7; 2]);
        }
        // The caller's refusal comes back as its own error; a room too small is refused
        // before a byte is written.
        let e = raw
            .encode_to("postcard", |_| Err::<(Vec<u8>, usize), _>("no room".into()))
            .unwrap_err();
        assert_eq!(e, "no room");
        let e = raw
            .encode_to("json", |_| Ok((vec![0u8; 4], 2)))
            .unwrap_err();
        assert!(
            e.contains("(4 bytes, the message at 2) cannot hold 13 bytes"),
            "{e}"
        );
        let e = raw
            .encode_to("postcard", |_| Ok((Vec::new(), usize::MAX)))
            .unwrap_err();
        assert!(e.contains("cannot hold"), "{e}");
        // A format the type lacks: `room` is never asked.
        let e = raw
            .encode_to("xml", |_| -> Result<(Vec<u8>, usize), String> {
                panic!("not asked")
            })
            .unwrap_err();
        assert!(e.contains("does not support the format 'xml'"), "{e}");
        // A panic in `room` unwinds on the caller's side, not through the C frame.
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            raw.encode_to("json", |_| -> Result<(Vec<u8>, usize), String> {
                panic!("from room")
            })
        }));
        assert_eq!(
            caught.unwrap_err().downcast_ref::<&str>(),
            Some(&"from room")
        );
        // Appending keeps what was there, and a failure leaves it as it was.
        let mut out = b"head".to_vec();
        raw.encode_into("postcard", &mut out).unwrap();
        assert_eq!(out[4..], raw.encode("postcard").unwrap());
        let before = out.clone();
        assert!(raw.encode_into("xml", &mut out).is_err());
        assert_eq!(out, before);
    }

    /// A message whose `encoded_len` is wrong (a bug in a hand-written impl).
    struct Liar;
    impl Message for Liar {
        fn type_name() -> &'static str {
            "test.Liar"
        }
        fn formats() -> &'static [&'static str] {
            &["raw"]
        }
        fn encode(&self, _: &str) -> Result<Vec<u8>, MessageError> {
            Ok(b"four".to_vec())
        }
        fn decode(_: &str, _: &[u8]) -> Result<Self, MessageError> {
            Ok(Liar)
        }
        fn encoded_len(&self, _: &str) -> Option<usize> {
            Some(2)
        }
    }

    #[test]
    fn an_encoded_len_that_disagrees_with_encode_is_an_error() {
        let raw = RawMessage::new(Arc::new(Liar));
        let e = raw.encode("raw").unwrap_err();
        assert!(e.contains("4 bytes encoded into room for 2"), "{e}");
    }

    static TRAPPED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

    unsafe extern "C" fn trap(_: *const c_void, _: StrView, _: RoomSink, _: ErrorSink) -> Status {
        TRAPPED.store(true, std::sync::atomic::Ordering::SeqCst);
        Status::FAILED
    }

    #[test]
    fn a_table_of_1_4_without_encode_to_is_encoded_and_copied() {
        let old: &'static TypeSupportVtable = Box::leak(Box::new(TypeSupportVtable {
            encode_to: trap,
            ..*type_support_as_1_4::<Hello>()
        }));
        let msg = Arc::new(Hello { text: "old".into() });
        // SAFETY: an `Arc<Hello>` pointer, and a table of `Hello` (a shorter copy).
        let raw = unsafe { RawMessage::from_raw(old, Arc::into_raw(msg).cast()) };
        let buf = raw
            .encode_to("json", |len| Ok((vec![0u8; 1 + len], 1)))
            .unwrap();
        assert_eq!(&buf[1..], br#"{"text":"old"}"#);
        assert_eq!(raw.encode("postcard").unwrap(), [3, b'o', b'l', b'd']);
        assert!(
            !TRAPPED.load(std::sync::atomic::Ordering::SeqCst),
            "read past the 1.4 table"
        );
        // What 1.3 added is still read from it.
        assert_eq!(schema_of(old), schema_of(type_support::<Hello>()));
        assert!(schema_of(old).is_some());
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
