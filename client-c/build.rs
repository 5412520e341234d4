//! The shared library's SONAME, `libinsitu.so.MAJOR`, as installed libraries carry it
//! (`client-c/install.sh` installs `libinsitu.so.VERSION` with the links the loader and the
//! linker look for).

fn main() {
    let major = std::env::var("CARGO_PKG_VERSION_MAJOR").unwrap_or_else(|_| "0".into());
    if std::env::var("CARGO_CFG_TARGET_OS").as_deref() == Ok("linux") {
        println!("cargo:rustc-cdylib-link-arg=-Wl,-soname,libinsitu.so.{major}");
    }
    println!("cargo:rerun-if-changed=build.rs");
}
