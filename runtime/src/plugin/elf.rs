//! Checks a library file before `dlopen` maps it: a truncated or foreign file must be
//! refused with a line naming what is wrong, not crash the process (a loadable segment
//! past the end of the file is mapped, and touching it raises SIGBUS).

use std::path::Path;

use object::elf::{FileHeader64, ELFCLASS32, ELFCLASS64, ELFMAG, ET_DYN, PT_LOAD};
use object::read::elf::{FileHeader, ProgramHeader};
use object::{Endianness, ReadCache, ReadRef};

/// The ELF machine this process runs on.
const MACHINE: (object::elf::Machine, &str) = if cfg!(target_arch = "x86_64") {
    (object::elf::EM_X86_64, "x86-64")
} else if cfg!(target_arch = "aarch64") {
    (object::elf::EM_AARCH64, "AArch64")
} else if cfg!(target_arch = "riscv64") {
    (object::elf::EM_RISCV, "RISC-V")
} else {
    (object::elf::EM_NONE, "this machine")
};

fn machine_name(machine: object::elf::Machine) -> String {
    match machine {
        object::elf::EM_X86_64 => "x86-64".to_owned(),
        object::elf::EM_386 => "x86 (32-bit)".to_owned(),
        object::elf::EM_AARCH64 => "AArch64".to_owned(),
        object::elf::EM_ARM => "ARM (32-bit)".to_owned(),
        object::elf::EM_RISCV => "RISC-V".to_owned(),
        other => format!("machine {}", other.0),
    }
}

/// `Ok` if `path` is a complete 64-bit ELF shared library for this machine.
pub(crate) fn check(path: &Path) -> Result<(), String> {
    let meta = std::fs::metadata(path).map_err(|e| format!("cannot open the library: {e}"))?;
    if meta.is_dir() {
        return Err(
            "is a directory, not a library file; give the path of the built .so".to_owned(),
        );
    }
    if !meta.is_file() {
        // A pipe would block `open`; a device is no library.
        return Err(
            "is not a regular file (a device, pipe or socket); give the path of the built .so"
                .to_owned(),
        );
    }
    let file = std::fs::File::open(path).map_err(|e| format!("cannot open the library: {e}"))?;
    let len = file
        .metadata()
        .map_err(|e| format!("cannot read the library's size: {e}"))?
        .len();
    if len == 0 {
        return Err("the file is empty (0 bytes), not a shared library; rebuild it (cargo build) or copy it again".to_owned());
    }
    let data = ReadCache::new(file);
    let data = &data;
    let magic = data.read_bytes_at(0, len.min(4)).unwrap_or_default();
    if magic != ELFMAG {
        let shown: String = magic
            .iter()
            .map(|&b| if b.is_ascii_graphic() { b as char } else { '.' })
            .collect();
        return Err(format!("not a shared library: the file starts with '{shown}', not an ELF header; give the path of the built .so"));
    }
    let class = data
        .read_bytes_at(4, 1)
        .ok()
        .and_then(|b| b.first().copied());
    if class == Some(ELFCLASS32.0) {
        return Err("is a 32-bit ELF library; this aimrt_main is 64-bit: build the library for the same target".to_owned());
    }
    if class != Some(ELFCLASS64.0) {
        return Err(format!(
            "has an ELF header of an unknown class ({class:?}); the file is damaged: rebuild it"
        ));
    }
    let header = FileHeader64::<Endianness>::parse(data).map_err(|_| {
        format!("the file ({len} bytes) ends inside its ELF header: it is truncated; rebuild it or copy it again")
    })?;
    let endian = header.endian().map_err(|_| {
        "its ELF header names an unknown byte order; the file is damaged: rebuild it".to_owned()
    })?;
    let machine = header.e_machine(endian);
    if MACHINE.0 != object::elf::EM_NONE && machine != MACHINE.0 {
        return Err(format!(
            "was built for {}, this machine is {}: build the library for this machine",
            machine_name(machine),
            MACHINE.1
        ));
    }
    if header.e_type(endian) != ET_DYN {
        return Err("is an ELF file but not a shared library (an executable or object file); build it as a cdylib".to_owned());
    }
    let segments = header.program_headers(endian, data).map_err(|_| {
        format!("its program headers lie past the end of the file ({len} bytes): it is truncated; rebuild it or copy it again")
    })?;
    for segment in segments {
        if segment.p_type(endian) != PT_LOAD {
            continue;
        }
        let end = segment
            .p_offset(endian)
            .checked_add(segment.p_filesz(endian));
        match end {
            Some(end) if end <= len => {}
            _ => {
                return Err(format!(
                    "is truncated: a loadable segment ends at byte {}, but the file has {len} bytes; rebuild it or copy it again",
                    end.map_or_else(|| "past 2^64".to_owned(), |e| e.to_string())
                ))
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn this_test_binary_is_not_a_library_and_garbage_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let exe = std::env::current_exe().unwrap();
        let bytes = std::fs::read(&exe).unwrap();
        let write = |name: &str, data: &[u8]| {
            let p = dir.path().join(name);
            std::fs::write(&p, data).unwrap();
            p
        };
        let cases: Vec<(std::path::PathBuf, &str)> = vec![
            (write("empty.so", b""), "empty (0 bytes)"),
            (write("text.so", b"hello, world\n"), "starts with 'hell'"),
            (write("short.so", &bytes[..3]), "starts with '.EL'"),
            (
                write("header.so", &bytes[..40]),
                "ends inside its ELF header",
            ),
            (
                write("class.so", &{
                    let mut b = bytes[..64].to_vec();
                    b[4] = ELFCLASS32.0;
                    b
                }),
                "32-bit",
            ),
        ];
        for (path, expected) in cases {
            let e = check(&path).unwrap_err();
            assert!(e.contains(expected), "{}: {e}", path.display());
        }
        // A test binary is an executable (PIE executables are ET_DYN too, so either is
        // fine) but never crashes the check; cut inside its segments it is truncated.
        let _ = check(&exe);
        let cut = write("cut.so", &bytes[..8192]);
        let e = check(&cut).unwrap_err();
        assert!(e.contains("truncated"), "{e}");
    }
}
