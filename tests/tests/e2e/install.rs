//! The C library as HPC users install it: `client-c/install.sh` into a prefix gives a
//! versioned shared library with its SONAME, `insitu.pc` and a CMake package; a C program
//! builds against it through pkg-config and through `find_package(insitu)`, and runs. And as
//! they misuse it: a buffer shorter than its dims say is refused unread (valgrind), a closed
//! handle is null.

use crate::common::{generator, small_config, viz};
use insitu_e2e::{bin_dir, build_c, ensure_built};
use insitu_testenv::{tool, Need};
use std::path::Path;
use std::process::{Command, Output};

fn ok(what: &str, o: Output) -> String {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(o.status.success(), "{what}: {text}");
    text
}

#[test]
fn the_installed_library_builds_through_pkg_config_and_cmake() {
    let (Some(cmake), Some(pkg_config), Some(cc)) = (
        tool("cmake", Need::CTools),
        tool("pkg-config", Need::CTools),
        tool("cc", Need::CTools),
    ) else {
        return;
    };
    ensure_built();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let tmp = tempfile::tempdir().unwrap();
    let prefix = tmp.path().join("prefix");
    ok(
        "install.sh",
        Command::new(root.join("client-c/install.sh"))
            .arg(&prefix)
            .env("INSITU_LIB_DIR", bin_dir().join("deps"))
            .output()
            .unwrap(),
    );
    let lib = prefix.join("lib");
    assert_eq!(
        std::fs::read_link(lib.join("libinsitu.so")).unwrap(),
        Path::new("libinsitu.so.0")
    );
    let soname = ok(
        "readelf",
        Command::new("readelf")
            .arg("-d")
            .arg(lib.join("libinsitu.so.0.1.0"))
            .output()
            .unwrap(),
    );
    assert!(soname.contains("[libinsitu.so.0]"), "{soname}");
    let probe = root.join("client-c/tests/installed");
    // pkg-config.
    let pc_path = lib.join("pkgconfig");
    let flags = ok(
        "pkg-config",
        Command::new(&pkg_config)
            .args(["--cflags", "--libs", "insitu"])
            .env("PKG_CONFIG_PATH", &pc_path)
            .output()
            .unwrap(),
    );
    let exe = tmp.path().join("probe_pc");
    ok(
        "cc through pkg-config",
        Command::new(&cc)
            .arg("-o")
            .arg(&exe)
            .arg(probe.join("probe.c"))
            .args(flags.split_whitespace())
            .output()
            .unwrap(),
    );
    let out = ok(
        "probe (pkg-config)",
        Command::new(&exe).arg("127.0.0.1:1").output().unwrap(),
    );
    assert!(
        out.contains("connect 2") && out.contains("unreachable"),
        "{out}"
    );
    // CMake.
    let build = tmp.path().join("build");
    ok(
        "cmake configure",
        Command::new(&cmake)
            .arg("-S")
            .arg(&probe)
            .arg("-B")
            .arg(&build)
            .arg(format!("-DCMAKE_PREFIX_PATH={}", prefix.display()))
            .output()
            .unwrap(),
    );
    ok(
        "cmake build",
        Command::new(&cmake)
            .arg("--build")
            .arg(&build)
            .output()
            .unwrap(),
    );
    let out = ok(
        "probe (CMake)",
        Command::new(build.join("probe"))
            .arg("127.0.0.1:1")
            .output()
            .unwrap(),
    );
    assert!(
        out.contains("connect 2") && out.contains("unreachable"),
        "{out}"
    );
}

/// A float buffer declared as doubles, pushed with its true length, is refused before it is
/// read: valgrind sees no invalid read; the handle `insitu_close` nulled refuses a push.
#[test]
fn a_short_buffer_is_refused_unread_and_a_closed_handle_is_null() {
    let (Some(valgrind), Some(cc)) = (tool("valgrind", Need::CTools), tool("cc", Need::CTools))
    else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let exe = tmp.path().join("short_buffer");
    build_c(
        &cc,
        "client-c/tests/installed/short_buffer.c",
        &exe,
        &["-g", "-Wall", "-Werror"],
    );
    let v = viz(&tmp.path().join("rec"), "127.0.0.1:0", tmp.path());
    let g = generator(&small_config(&v.addr, "block", 4), tmp.path(), &[]);
    let out = Command::new(valgrind)
        .args(["--error-exitcode=9", "--errors-for-leak-kinds=none", "-q"])
        .arg(&exe)
        .arg(&g.addr)
        .output()
        .unwrap();
    let text = ok("valgrind short_buffer", out);
    assert!(
        text.contains("short 1 data_bytes 16384 is not the 32768 bytes of a brick of [16, 16, 16] points of 8-byte values"),
        "{text}"
    );
    assert!(text.contains("closed 1 client is null"), "{text}");
    assert!(!text.contains("Invalid read"), "{text}");
    g.terminate();
    v.terminate();
}
