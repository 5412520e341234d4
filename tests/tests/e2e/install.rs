//! The C library as HPC users install it: `client-c/install.sh` into a prefix gives a
//! versioned shared library with its SONAME, `insitu.pc` and a CMake package; a C program
//! builds against it through pkg-config and through `find_package(insitu)`, and runs.

use insitu_e2e::{bin_dir, ensure_built};
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
        tool("cmake", Need::Cmake),
        tool("pkg-config", Need::Cmake),
        tool("cc", Need::Cmake),
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
