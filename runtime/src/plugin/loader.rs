//! Opens shared libraries and checks their descriptor before running any of their code.
//!
//! Libraries are opened with `RTLD_NOW | RTLD_LOCAL` and never closed (leaked on purpose:
//! their threads and tasks may run until the process exits).
#![allow(unsafe_code)]

use std::path::{Path, PathBuf};
use std::sync::Arc;

use aimrt_plugin_api::ffi::{
    unpad, ErrorSink, HostInit, LibraryDescriptor, RawLogger, RawModule, RawPlugin, Status,
    StrView, TypeSupportVtable, ABI_MAJOR, ABI_MINOR, API_VERSION, ENTRY_SYMBOL, MAGIC, TARGET,
};
use aimrt_plugin_api::LogLevel;

use crate::log::{LogHub, Logger};
use crate::Error;

/// A loaded, checked and initialised library.
pub(crate) struct Library {
    pub(crate) path: PathBuf,
    /// A copy of the library's descriptor; entries past its `size` are empty.
    desc: LibraryDescriptor,
}

// SAFETY: the descriptor holds function pointers into a library that is never unloaded.
unsafe impl Send for Library {}
// SAFETY: see above.
unsafe impl Sync for Library {}

fn fail(what: &str, path: &Path, message: impl Into<String>) -> Error {
    Error::Library {
        what: what.to_owned(),
        path: path.display().to_string(),
        message: message.into(),
    }
}

impl Library {
    /// Opens `path` (relative to the working directory), checks the descriptor, then
    /// initialises the library with its own logger named `log_name`.
    pub(crate) fn open(
        what: &str,
        path: &str,
        log_name: &str,
        core_lvl: LogLevel,
        hub: &Arc<LogHub>,
    ) -> Result<Library, Error> {
        let given = Path::new(path);
        let full = std::fs::canonicalize(given).map_err(|e| {
            let cwd = std::env::current_dir().map(|d| d.display().to_string()).unwrap_or_default();
            fail(what, given, format!("cannot open the library: {e}; check the path (relative paths start at the working directory {cwd}) and that it was built (cargo build --workspace)"))
        })?;
        super::elf::check(&full).map_err(|m| fail(what, &full, m))?;
        // SAFETY: loading a library runs its initialisers; aimrt-rs libraries are Rust
        // cdylibs whose only static initialisers are std's. This is the documented
        // trust boundary: aimrt_main runs the libraries its config names.
        let lib = unsafe {
            libloading::os::unix::Library::open(
                Some(&full),
                libloading::os::unix::RTLD_NOW | libloading::os::unix::RTLD_LOCAL,
            )
        }
        .map_err(|e| fail(what, &full, format!("cannot load the library: {e}")))?;
        // SAFETY: we only take the symbol's address; it is read below after checks.
        let sym = unsafe { lib.get::<*const LibraryDescriptor>(ENTRY_SYMBOL.as_bytes()) };
        let addr: *const LibraryDescriptor = match sym {
            // For a data symbol, the raw symbol value is its address.
            Ok(s) => s.into_raw().cast(),
            Err(_) => {
                return Err(fail(
                    what,
                    &full,
                    format!("no aimrt-rs entry symbol '{ENTRY_SYMBOL}'; build it as a cdylib that calls aimrt_plugin_api::export_modules! or export_plugin!"),
                ))
            }
        };
        // Never unload: threads and tasks of the library may run until the process exits.
        std::mem::forget(lib);
        // SAFETY: the symbol is at least 8 bytes if it is anything we know; a foreign
        // symbol of that name smaller than that is not a case we can detect.
        let magic = unsafe { addr.cast::<u64>().read_unaligned() };
        if magic != MAGIC {
            return Err(fail(what, &full, format!("'{ENTRY_SYMBOL}' is not an aimrt-rs descriptor (bad magic); rebuild it against aimrt-plugin-api {API_VERSION}")));
        }
        // SAFETY: magic matched, so the frozen prefix (magic, major, minor, size, unwind) is there.
        let (major, minor, size, unwind) = unsafe {
            let p = addr.cast::<u32>();
            (
                p.add(2).read(),
                p.add(3).read(),
                p.add(4).read(),
                p.add(5).read(),
            )
        };
        if major != ABI_MAJOR {
            return Err(fail(what, &full, format!(
                "was built against ABI {major}.{minor}; this aimrt_main needs {ABI_MAJOR}.x — rebuild it against aimrt-plugin-api {API_VERSION}"
            )));
        }
        if minor > ABI_MINOR {
            return Err(fail(what, &full, format!(
                "was built against ABI {major}.{minor}, newer than this aimrt_main ({ABI_MAJOR}.{ABI_MINOR}) — update aimrt_main or rebuild the library against aimrt-plugin-api {API_VERSION}"
            )));
        }
        let needed = if minor >= 3 {
            size_of::<LibraryDescriptor>()
        } else {
            LibraryDescriptor::SIZE_1_2
        };
        if (size as usize) < needed {
            return Err(fail(what, &full, format!("its descriptor is {size} bytes, smaller than ABI {major}.{minor} requires; rebuild it against aimrt-plugin-api {API_VERSION}")));
        }
        // A library of an older minor has a shorter descriptor: copy what it has, and read
        // the entries it lacks as empty.
        let mut desc = LibraryDescriptor::empty();
        let have = (size as usize).min(size_of::<LibraryDescriptor>());
        // SAFETY: major, minor and size checked: `have` bytes of static descriptor are
        // there; `desc` is a plain `repr(C)` struct of integers, byte arrays and nullable
        // function pointers (for which every bit pattern the library wrote is one it
        // meant), at least `have` bytes long.
        unsafe {
            std::ptr::copy_nonoverlapping(
                addr.cast::<u8>(),
                (&mut desc as *mut LibraryDescriptor).cast::<u8>(),
                have,
            );
        }
        let target = unpad(&desc.target);
        if target != TARGET {
            return Err(fail(what, &full, format!("was built for target '{target}', this aimrt_main for '{TARGET}'; rebuild it for {TARGET}")));
        }
        if unwind == 0 {
            return Err(fail(what, &full, "was built with panic = \"abort\", so a panic in it would kill the process; build it with panic = \"unwind\" (remove panic = \"abort\" from its Cargo profile)"));
        }
        let init = desc.init.ok_or_else(|| {
            fail(
                what,
                &full,
                "its descriptor has no init entry; rebuild it with the export macros",
            )
        })?;
        let logger = RawLogger::leak(Logger::new(log_name, core_lvl, hub));
        let host = HostInit {
            header: aimrt_plugin_api::ffi::Header::of::<HostInit>(),
            library_logger: logger,
        };
        // SAFETY: checked descriptor; `host` outlives the call.
        let status = unsafe { init(&host) };
        if !status.is_ok() {
            return Err(fail(
                what,
                &full,
                format!("library initialisation failed: {status}"),
            ));
        }
        Ok(Library { path: full, desc })
    }

    /// The message type tables the library offers as a type support package (ABI 1.3;
    /// empty for older libraries and for libraries that offer none).
    pub(crate) fn type_supports(&self) -> Vec<&'static TypeSupportVtable> {
        let (Some(count), Some(at)) = (self.desc.type_support_count, self.desc.type_support) else {
            return Vec::new();
        };
        // SAFETY: entries of a checked descriptor of a never-unloaded library; the tables
        // they return are static.
        let n = unsafe { count() };
        (0..n)
            // SAFETY: as above; a null pointer is skipped.
            .filter_map(|i| unsafe { at(i).as_ref() })
            .collect()
    }

    /// The names of the modules the library exports (empty if it exports none).
    pub(crate) fn module_names(&self) -> Vec<String> {
        let (Some(count), Some(name)) = (self.desc.module_count, self.desc.module_name) else {
            return Vec::new();
        };
        // SAFETY: entries of a checked descriptor; views copied at once.
        let n = unsafe { count() };
        // SAFETY: as above, index in range.
        (0..n)
            .map(|i| unsafe { name(i).to_string_lossy() })
            .collect()
    }

    /// Creates the named module.
    pub(crate) fn create_module(&self, name: &str) -> Result<RawModule, String> {
        let create = self
            .desc
            .create_module
            .ok_or("the library exports no modules (export_modules!)")?;
        let mut out = std::mem::MaybeUninit::<RawModule>::uninit();
        let mut err = String::new();
        // SAFETY: checked descriptor; the name view, `out` and the sink outlive the call.
        let status = unsafe { create(StrView::new(name), out.as_mut_ptr(), sink(&mut err)) };
        created(status, out, err)
    }

    /// Whether the library exports a plugin.
    pub(crate) fn has_plugin(&self) -> bool {
        self.desc.create_plugin.is_some()
    }

    /// Creates the library's plugin.
    pub(crate) fn create_plugin(&self) -> Result<RawPlugin, String> {
        let create = self
            .desc
            .create_plugin
            .ok_or("the library exports no plugin (export_plugin!)")?;
        let mut out = std::mem::MaybeUninit::<RawPlugin>::uninit();
        let mut err = String::new();
        // SAFETY: checked descriptor; `out` and the sink outlive the call.
        let status = unsafe { create(out.as_mut_ptr(), sink(&mut err)) };
        created(status, out, err)
    }
}

/// The object a `create_*` entry wrote, or its error message.
fn created<T>(status: Status, out: std::mem::MaybeUninit<T>, err: String) -> Result<T, String> {
    if status.is_ok() {
        // SAFETY: a library's `create_*` entry writes `out` exactly when it returns OK.
        Ok(unsafe { out.assume_init() })
    } else if err.is_empty() {
        Err(format!("returned {status}"))
    } else {
        Err(err)
    }
}

fn sink(out: &mut String) -> ErrorSink {
    unsafe extern "C" fn set(ctx: *mut std::ffi::c_void, message: StrView) {
        // SAFETY: `ctx` is the `&mut String` of `sink`, alive during the call.
        let s = unsafe { &mut *ctx.cast::<String>() };
        // SAFETY: the view is valid for this call.
        *s = unsafe { message.to_string_lossy() };
    }
    ErrorSink {
        ctx: (out as *mut String).cast(),
        set,
    }
}
