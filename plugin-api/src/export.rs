//! `export_modules!` and `export_plugin!`: the entry point of a module or plugin library.
//!
//! Use them only in a `cdylib`-only crate: two rlibs that both define the entry symbol
//! link into one binary without an error, and one silently replaces the other. Code that
//! is also linked statically keeps a plain Rust function (`pub fn plugin()`), and a
//! cdylib crate of a few lines exports it.

/// Exports module types from a `cdylib`.
///
/// `export_modules!(A, B)` exports types implementing [`Module`](crate::Module) +
/// `Default`, named after the type; `export_modules!("Name" => constructor, …)` names them
/// explicitly (`constructor: fn() -> impl Module`). The name must equal
/// `Module::info().name`.
///
/// ```ignore
/// aimrt_plugin_api::export_modules!(HelloModule);
/// ```
#[macro_export]
macro_rules! export_modules {
    ($($ty:ident),+ $(,)?) => {
        $crate::export_modules!($(stringify!($ty) => <$ty as ::core::default::Default>::default),+);
    };
    ($($name:expr => $ctor:expr),+ $(,)?) => {
        const _: () = {
            $crate::__module_entries!($($name => $ctor),+);

            #[allow(non_upper_case_globals, unsafe_code)]
            #[unsafe(no_mangle)]
            pub static aimrt_rs_library: $crate::ffi::LibraryDescriptor = $crate::ffi::LibraryDescriptor {
                module_count: Some(__aimrt_module_count),
                module_name: Some(__aimrt_module_name),
                create_module: Some(__aimrt_create_module),
                ..$crate::ffi::LibraryDescriptor::new(cfg!(panic = "unwind"))
            };
        };
    };
}

/// The module list and the three descriptor entries of [`export_modules!`].
#[doc(hidden)]
#[macro_export]
macro_rules! __module_entries {
    ($($name:expr => $ctor:expr),+) => {
        static __AIMRT_MODULES: &[(&str, $crate::__private::ModuleCtor)] = &[
            $(($name, || ::std::boxed::Box::new(($ctor)()) as ::std::boxed::Box<dyn $crate::Module>)),+
        ];

        unsafe extern "C" fn __aimrt_module_count() -> usize {
            __AIMRT_MODULES.len()
        }

        unsafe extern "C" fn __aimrt_module_name(index: usize) -> $crate::ffi::StrView {
            $crate::__private::module_name(__AIMRT_MODULES, index)
        }

        unsafe extern "C" fn __aimrt_create_module(
            name: $crate::ffi::StrView,
            out: *mut $crate::ffi::RawModule,
            err: $crate::ffi::ErrorSink,
        ) -> $crate::ffi::Status {
            // SAFETY: the host passes a valid name view and a writable `out`
            // (the descriptor's contract).
            unsafe { $crate::__private::create_module(__AIMRT_MODULES, name, out, err) }
        }
    };
}

/// [`export_modules!`] as a library of ABI 1.`minor` (≤ 2) was built: its descriptor
/// declares that minor and has the 1.2 layout. For tests that old libraries still load.
#[doc(hidden)]
#[macro_export]
macro_rules! __export_modules_as_1_2 {
    ($minor:expr; $($ty:ident),+ $(,)?) => {
        const _: () = {
            $crate::__module_entries!($(stringify!($ty) => <$ty as ::core::default::Default>::default),+);

            #[allow(non_upper_case_globals, unsafe_code)]
            #[unsafe(no_mangle)]
            pub static aimrt_rs_library: $crate::__private::DescriptorUpTo12 =
                $crate::__private::DescriptorUpTo12::of(
                    $crate::ffi::LibraryDescriptor {
                        module_count: Some(__aimrt_module_count),
                        module_name: Some(__aimrt_module_name),
                        create_module: Some(__aimrt_create_module),
                        ..$crate::ffi::LibraryDescriptor::new(cfg!(panic = "unwind"))
                    },
                    $minor,
                );
        };
    };
}

/// [`export_modules!`] as a library of ABI 1.`minor` (≥ 3, whose descriptor has today's
/// layout) was built: its descriptor declares that minor. For tests that old libraries
/// still load.
#[doc(hidden)]
#[macro_export]
macro_rules! __export_modules_with {
    ($minor:expr; $($ty:ident),+ $(,)?) => {
        const _: () = {
            $crate::__module_entries!($(stringify!($ty) => <$ty as ::core::default::Default>::default),+);

            #[allow(non_upper_case_globals, unsafe_code)]
            #[unsafe(no_mangle)]
            pub static aimrt_rs_library: $crate::ffi::LibraryDescriptor = $crate::ffi::LibraryDescriptor {
                abi_minor: $minor,
                module_count: Some(__aimrt_module_count),
                module_name: Some(__aimrt_module_name),
                create_module: Some(__aimrt_create_module),
                ..$crate::ffi::LibraryDescriptor::new(cfg!(panic = "unwind"))
            };
        };
    };
}

/// Exports a plugin from a `cdylib`: `export_plugin!(constructor)` with
/// `constructor: fn() -> Box<dyn Plugin>`.
///
/// ```ignore
/// aimrt_plugin_api::export_plugin!(my_executors::plugin);
/// ```
#[macro_export]
macro_rules! export_plugin {
    ($ctor:path) => {
        $crate::__export_plugin_with!(create_plugin, $crate::ffi::ABI_MINOR; $ctor);
    };
}

/// Exports a plugin as a library built against ABI 1.3 would: the descriptor says 1.3 and
/// the plugin table has the 1.3 layout (no `post_start`). For the fixture that proves
/// such plugins load on a newer host.
#[doc(hidden)]
#[macro_export]
macro_rules! __export_plugin_as_1_3 {
    ($ctor:path) => {
        $crate::__export_plugin_with!(create_plugin_as_1_3, 3; $ctor);
    };
}

/// The entry of a plugin library: `__private::$create` makes the plugin, the descriptor
/// declares ABI minor `$minor`.
#[doc(hidden)]
#[macro_export]
macro_rules! __export_plugin_with {
    ($create:ident, $minor:expr; $ctor:path) => {
        const _: () = {
            unsafe extern "C" fn __aimrt_create_plugin(
                out: *mut $crate::ffi::RawPlugin,
                err: $crate::ffi::ErrorSink,
            ) -> $crate::ffi::Status {
                // SAFETY: the host passes a writable `out` (the descriptor's contract).
                unsafe { $crate::__private::$create($ctor, out, err) }
            }

            #[allow(non_upper_case_globals, unsafe_code)]
            #[unsafe(no_mangle)]
            pub static aimrt_rs_library: $crate::ffi::LibraryDescriptor =
                $crate::ffi::LibraryDescriptor {
                    abi_minor: $minor,
                    create_plugin: Some(__aimrt_create_plugin),
                    ..$crate::ffi::LibraryDescriptor::new(cfg!(panic = "unwind"))
                };
        };
    };
}

/// Exports message types from a `cdylib` as a type support package (ABI 1.3; AimRT's
/// `type_support_pkgs`): plugins load it by path and find its types by name, e.g. to
/// record or echo topics whose Rust type they do not know.
///
/// ```ignore
/// aimrt_plugin_api::export_type_support!(ExampleEventMsg, GetFooDataReq, GetFooDataRsp);
/// ```
#[macro_export]
macro_rules! export_type_support {
    ($($ty:ty),+ $(,)?) => {
        $crate::__export_type_support_with!($crate::ffi::ABI_MINOR, type_support; $($ty),+);
    };
}

/// Exports a type support package as a library built against ABI 1.4 would: the
/// descriptor says 1.4 and each type's table has the 1.4 layout (no `encode_to`). For the
/// fixture that proves such packages still work on a newer host.
#[doc(hidden)]
#[macro_export]
macro_rules! __export_type_support_as_1_4 {
    ($($ty:ty),+ $(,)?) => {
        $crate::__export_type_support_with!(4, type_support_as_1_4; $($ty),+);
    };
}

/// The entry of a type support package: `__private::$table::<T>` gives each type's
/// table, the descriptor declares ABI minor `$minor`.
#[doc(hidden)]
#[macro_export]
macro_rules! __export_type_support_with {
    ($minor:expr, $table:ident; $($ty:ty),+) => {
        const _: () = {
            static __AIMRT_TYPES: &[fn() -> &'static $crate::ffi::TypeSupportVtable] = &[
                $($crate::__private::$table::<$ty>),+
            ];

            unsafe extern "C" fn __aimrt_type_support_count() -> usize {
                __AIMRT_TYPES.len()
            }

            unsafe extern "C" fn __aimrt_type_support(
                index: usize,
            ) -> *const $crate::ffi::TypeSupportVtable {
                $crate::__private::type_support_at(__AIMRT_TYPES, index)
            }

            #[allow(non_upper_case_globals, unsafe_code)]
            #[unsafe(no_mangle)]
            pub static aimrt_rs_library: $crate::ffi::LibraryDescriptor =
                $crate::ffi::LibraryDescriptor {
                    abi_minor: $minor,
                    type_support_count: Some(__aimrt_type_support_count),
                    type_support: Some(__aimrt_type_support),
                    ..$crate::ffi::LibraryDescriptor::new(cfg!(panic = "unwind"))
                };
        };
    };
}
