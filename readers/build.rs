//! Links ADIOS2's C library when the `adios2` feature is on. Where it lies, first found:
//! `ADIOS2_DIR` (an install prefix with `lib/` or `lib64/`, a directory holding
//! `libadios2_c.so` itself as the PyPI wheel's package directory does, or the CMake config
//! directory `<prefix>/lib/cmake/adios2`), else the linker's default paths. The directory is
//! written into the readers' own test binaries' run path and passed to dependents as
//! `DEP_ADIOS2_C_LIBDIR` (the `links` key), so their binaries find it without
//! `LD_LIBRARY_PATH`. Where the library's header declares the text-attribute calls that ask
//! for lengths first, `cfg(adios2_string_data)` turns on reading text attributes (openPMD).

use std::path::{Path, PathBuf};

fn holds_library(dir: &Path) -> bool {
    ["libadios2_c.so", "libadios2_c.dylib"]
        .iter()
        .any(|f| dir.join(f).exists())
}

/// The directory holding `libadios2_c` for an `ADIOS2_DIR` of any of the shapes above.
fn library_dir(root: &Path) -> Option<PathBuf> {
    let mut candidates = vec![
        root.to_path_buf(),
        root.join("lib"),
        root.join("lib64"),
        root.join("adios2"),
    ];
    // <prefix>/lib/cmake/adios2 → <prefix>/lib
    if let Some(lib) = root.parent().and_then(Path::parent) {
        candidates.push(lib.to_path_buf());
    }
    candidates.into_iter().find(|d| holds_library(d))
}

/// Whether the C API's header beside `root` (or in the system's include directories)
/// declares the length-first text attribute calls (`adios2_attribute_string_data`): then
/// `cfg(adios2_string_data)`, and openPMD's text attributes can be read.
fn string_data(root: Option<&Path>) -> bool {
    let header = "adios2/c/adios2_c_attribute.h";
    let mut dirs: Vec<PathBuf> = Vec::new();
    if let Some(root) = root {
        dirs.push(root.join("include"));
        // <prefix>/lib/cmake/adios2 → <prefix>/include
        if let Some(prefix) = root.ancestors().nth(3) {
            dirs.push(prefix.join("include"));
        }
    }
    dirs.extend(["/usr/include", "/usr/local/include"].map(PathBuf::from));
    dirs.iter().any(|d| {
        let Ok(text) = std::fs::read_to_string(d.join(header)) else {
            return false;
        };
        println!("cargo:rerun-if-changed={}", d.join(header).display());
        text.contains("adios2_attribute_string_data_array")
    })
}

fn main() {
    println!("cargo:rerun-if-env-changed=ADIOS2_DIR");
    println!("cargo::rustc-check-cfg=cfg(adios2_string_data)");
    if std::env::var_os("CARGO_FEATURE_ADIOS2").is_none() {
        return;
    }
    let root = std::env::var_os("ADIOS2_DIR").map(PathBuf::from);
    if string_data(root.as_deref()) {
        println!("cargo:rustc-cfg=adios2_string_data");
    }
    if let Some(root) = root {
        let Some(dir) = library_dir(&root) else {
            println!(
                "cargo:warning=ADIOS2_DIR={} holds no libadios2_c (looked in it, lib/, lib64/, \
                 adios2/ and two levels up); linking from the default paths",
                root.display()
            );
            println!("cargo:rustc-link-lib=dylib=adios2_c");
            return;
        };
        println!("cargo:rustc-link-search=native={}", dir.display());
        println!("cargo:rustc-link-arg=-Wl,-rpath,{}", dir.display());
        println!("cargo:libdir={}", dir.display());
    }
    println!("cargo:rustc-link-lib=dylib=adios2_c");
}
