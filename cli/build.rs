//! With the `adios2` feature: ADIOS2's library directory (found by insitu-readers' build
//! script, passed on through its `links` key) written into the binaries' run path, so they
//! start without `LD_LIBRARY_PATH`.

fn main() {
    println!("cargo:rerun-if-env-changed=DEP_ADIOS2_C_LIBDIR");
    if let Ok(dir) = std::env::var("DEP_ADIOS2_C_LIBDIR") {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    }
}
