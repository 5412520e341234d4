//! What a test needs from the machine beyond the repository, and what happens without it.
//!
//! Four needs ([`Need`]): the real volumes and their transfer functions, a GPU adapter (any
//! Vulkan driver; Mesa's lavapipe is enough), Open MPI, and Chromium with its driver. A test
//! whose need is not met is skipped: the lookup returns `None` and, when the test binary
//! exits, one line says how many tests it skipped for what and how to get it. A fresh clone
//! with nothing installed beside Rust and a C compiler therefore passes; everything those
//! tests cover is also covered by synthetic fields.
//!
//! Where a need must be met (CI, which installs and provides all four), `INSITU_REQUIRE` names
//! them (`data,gpu,mpi,browser`, or `all`) and a missing one fails its test with a message
//! naming what was looked for.
//!
//! Real volumes are looked up, in order, in
//!
//! 1. `$INSITU_DATA_DIR` (volumes) or `$INSITU_TF_DIR` (transfer functions), when set;
//! 2. `data/` (volumes) or `data/tf/` (transfer functions) in the repository, where
//!    `scripts/fetch-data.sh` puts the volumes;
//! 3. `../shared/data` or `../shared/tf` beside the repository.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, Once};

/// Something a test needs from the machine.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Need {
    /// The real volumes and their transfer functions (docs/data.md).
    Data,
    /// A GPU adapter for the wgpu path (any Vulkan driver; lavapipe will do).
    Gpu,
    /// Open MPI's `mpicc` and `mpirun`.
    Mpi,
    /// Debian's `chromium` and `chromedriver`.
    Browser,
    /// The readers' test files written by the reference libraries, and their venv
    /// (`scripts/write-fixtures.sh`).
    Fixtures,
    /// Debian's `ffmpeg` (with `ffprobe`).
    Ffmpeg,
    /// Debian's `gfortran` (behind Open MPI's `mpifort`).
    Fortran,
    /// `cmake`, `pkg-config` and `valgrind`, to build against the installed C library and check
    /// its memory use.
    CTools,
    /// The Python package built from `python/` and installed in the fixtures' venv
    /// (`scripts/build-python.sh`).
    Python,
    /// Debian's `slurm-wlm` and `munge`, and root to start a one-host cluster.
    Slurm,
}

const NEEDS: [Need; 10] = [
    Need::Data,
    Need::Gpu,
    Need::Mpi,
    Need::Browser,
    Need::Fixtures,
    Need::Ffmpeg,
    Need::Fortran,
    Need::CTools,
    Need::Python,
    Need::Slurm,
];

impl Need {
    /// The name `INSITU_REQUIRE` uses.
    pub fn name(self) -> &'static str {
        match self {
            Need::Data => "data",
            Need::Gpu => "gpu",
            Need::Mpi => "mpi",
            Need::Browser => "browser",
            Need::Fixtures => "fixtures",
            Need::Ffmpeg => "ffmpeg",
            Need::Fortran => "fortran",
            Need::CTools => "ctools",
            Need::Python => "python",
            Need::Slurm => "slurm",
        }
    }

    /// How to meet it.
    pub fn remedy(self) -> &'static str {
        match self {
            Need::Data => "scripts/fetch-data.sh",
            Need::Gpu => "apt-get install mesa-vulkan-drivers",
            Need::Mpi => "apt-get install openmpi-bin libopenmpi-dev",
            Need::Browser => "apt-get install chromium chromium-driver",
            Need::Fixtures => "scripts/write-fixtures.sh",
            Need::Ffmpeg => "apt-get install ffmpeg",
            Need::Fortran => "apt-get install gfortran",
            Need::CTools => "apt-get install cmake pkg-config valgrind",
            Need::Python => "scripts/build-python.sh",
            Need::Slurm => "apt-get install slurm-wlm munge, as root",
        }
    }

    fn index(self) -> usize {
        self as usize
    }

    /// Whether `INSITU_REQUIRE` makes this need a failure rather than a skip.
    pub fn required(self) -> bool {
        std::env::var("INSITU_REQUIRE").is_ok_and(|v| requires(&v, self))
    }
}

fn requires(list: &str, need: Need) -> bool {
    list.split(',')
        .map(str::trim)
        .any(|n| n == "all" || n == need.name())
}

/// The tests skipped, by need (a test is named by its thread, as the harness names it; one
/// test that looks up several missing files counts once).
static SKIPPED: Mutex<BTreeSet<(usize, String)>> = Mutex::new(BTreeSet::new());
static SUMMARY: Once = Once::new();

/// Records that the calling test is skipped because `need` is not met (`what` says what was
/// looked for) and returns `None`, for `let Some(x) = … else { return };`.
///
/// # Panics
/// When `INSITU_REQUIRE` names `need`, with `what` and the remedy in the message.
pub fn skip<T>(need: Need, what: &str) -> Option<T> {
    if need.required() {
        panic!(
            "{what} (INSITU_REQUIRE names {}; {})",
            need.name(),
            need.remedy()
        );
    }
    let test = std::thread::current().name().unwrap_or("main").to_owned();
    SKIPPED
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .insert((need.index(), test));
    SUMMARY.call_once(|| {
        // SAFETY: `summary` is an `extern "C" fn()` that reads a static and writes to stderr,
        // both valid until the process ends; registering it has no other precondition.
        #[allow(unsafe_code)]
        unsafe {
            libc::atexit(summary);
        }
    });
    None
}

/// Printed when the test binary exits: the harness captures what tests print and ends with
/// `process::exit`, which runs `atexit` handlers.
extern "C" fn summary() {
    let skipped = SKIPPED.lock().unwrap_or_else(|e| e.into_inner());
    let parts: Vec<String> = NEEDS
        .iter()
        .filter_map(|&n| {
            let k = skipped.iter().filter(|(i, _)| *i == n.index()).count();
            (k > 0).then(|| format!("{k} need {} ({})", n.name(), n.remedy()))
        })
        .collect();
    eprintln!(
        "note: tests skipped for what this machine lacks: {}",
        parts.join("; ")
    );
}

/// The repository's root (this crate sits one level below it).
fn repo() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

/// The folders searched for volumes, in order (see the crate documentation).
pub fn data_dirs() -> Vec<PathBuf> {
    dirs("INSITU_DATA_DIR", "data", "../shared/data")
}

/// The folders searched for transfer functions, in order (see the crate documentation).
pub fn tf_dirs() -> Vec<PathBuf> {
    dirs("INSITU_TF_DIR", "data/tf", "../shared/tf")
}

fn dirs(var: &str, inside: &str, beside: &str) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = std::env::var_os(var)
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .into_iter()
        .collect();
    out.push(repo().join(inside));
    out.push(repo().join(beside));
    out
}

/// The path of the real volume `name` (e.g. `teapot_256x256x178_uint8.raw`), or `None` (the
/// test skips) when it is in none of [`data_dirs`].
///
/// # Panics
/// As [`skip`], when the volume is missing and data is required.
pub fn data_file(name: &str) -> Option<PathBuf> {
    find(name, &data_dirs())
}

/// The path of the transfer function `name` (e.g. `teapot.json`), or `None` (the test skips)
/// when it is in none of [`tf_dirs`].
///
/// # Panics
/// As [`data_file`].
pub fn tf_file(name: &str) -> Option<PathBuf> {
    find(name, &tf_dirs())
}

fn find(name: &str, dirs: &[PathBuf]) -> Option<PathBuf> {
    locate(name, dirs).or_else(|| {
        let searched: Vec<String> = dirs.iter().map(|d| d.display().to_string()).collect();
        skip(
            Need::Data,
            &format!("{name} is in none of {}", searched.join(", ")),
        )
    })
}

/// The first `dir/name` that is a file.
fn locate(name: &str, dirs: &[PathBuf]) -> Option<PathBuf> {
    dirs.iter().map(|d| d.join(name)).find(|p| p.is_file())
}

/// The folder of the readers' test files (`$INSITU_FIXTURE_DIR`, else `target/fixtures` in
/// the repository) when it holds their `manifest.json`, or `None` (the test skips).
///
/// # Panics
/// As [`skip`], when the files are missing and fixtures are required.
pub fn fixture_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("INSITU_FIXTURE_DIR")
        .filter(|v| !v.is_empty())
        .map_or_else(|| repo().join("target/fixtures"), PathBuf::from);
    if dir.join("manifest.json").is_file() {
        return Some(dir);
    }
    skip(
        Need::Fixtures,
        &format!("{} holds no manifest.json", dir.display()),
    )
}

/// The Python of the fixtures' venv (`target/fixtures-venv`, with numpy, pandas, Pillow and
/// the reference libraries), or `None` (the test skips).
///
/// # Panics
/// As [`skip`], when it is missing and fixtures are required.
pub fn fixture_python() -> Option<PathBuf> {
    file(
        &repo().join("target/fixtures-venv/bin/python"),
        Need::Fixtures,
    )
}

/// The fixtures' venv Python when the package `insitu` (built from `python/` by
/// `scripts/build-python.sh`) imports there, or `None` (the test skips for [`Need::Python`]).
///
/// # Panics
/// As [`skip`], when the package is missing and Python is required.
pub fn python_package() -> Option<PathBuf> {
    let python = repo().join("target/fixtures-venv/bin/python");
    let imports = std::process::Command::new(&python)
        .args(["-c", "import insitu"])
        .output()
        .is_ok_and(|o| o.status.success());
    if imports {
        Some(python)
    } else {
        skip(
            Need::Python,
            &format!("the package insitu does not import in {}", python.display()),
        )
    }
}

/// The program `name` on `PATH`, or `None` (the test skips for `need`).
///
/// # Panics
/// As [`skip`], when the program is missing and `need` is required.
pub fn tool(name: &str, need: Need) -> Option<PathBuf> {
    let found = std::env::var_os("PATH").and_then(|paths| {
        let dirs: Vec<PathBuf> = std::env::split_paths(&paths).collect();
        locate(name, &dirs)
    });
    found.or_else(|| skip(need, &format!("{name} is not on PATH")))
}

/// The file at `path`, or `None` (the test skips for `need`).
///
/// # Panics
/// As [`skip`], when the file is missing and `need` is required.
pub fn file(path: &Path, need: Need) -> Option<PathBuf> {
    if path.is_file() {
        return Some(path.to_path_buf());
    }
    skip(need, &format!("{} is missing", path.display()))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_first_folder_holding_the_file_wins() {
        let root = std::env::temp_dir().join(format!("insitu-testenv-{}", std::process::id()));
        let (a, b, c) = (root.join("a"), root.join("b"), root.join("c"));
        for d in [&a, &b, &c] {
            std::fs::create_dir_all(d).unwrap();
        }
        std::fs::write(b.join("v.raw"), b"x").unwrap();
        std::fs::write(c.join("v.raw"), b"x").unwrap();
        let dirs = vec![a.clone(), b.clone(), c];
        assert_eq!(locate("v.raw", &dirs), Some(b.join("v.raw")));
        assert_eq!(locate("w.raw", &dirs), None);
        // A folder of that name is not a file.
        std::fs::create_dir_all(a.join("d.raw")).unwrap();
        assert_eq!(locate("d.raw", &dirs), None);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn the_variable_comes_first_then_inside_then_beside() {
        std::env::set_var("INSITU_TESTENV_PROBE", "/somewhere");
        let found = dirs("INSITU_TESTENV_PROBE", "data", "../shared/data");
        assert_eq!(found.len(), 3);
        assert_eq!(found[0], PathBuf::from("/somewhere"));
        assert!(found[1].ends_with("data"));
        assert!(found[2].ends_with("../shared/data"));
        assert_eq!(dirs("INSITU_TESTENV_UNSET_PROBE", "data", "x").len(), 2);
    }

    #[test]
    fn require_names_needs_or_all() {
        assert!(requires("data,gpu", Need::Gpu));
        assert!(requires("data, mpi", Need::Mpi));
        assert!(!requires("data,gpu", Need::Browser));
        assert!(requires("all", Need::Browser));
        assert!(!requires("", Need::Data));
        assert!(!requires("gpus", Need::Gpu));
    }
}
