//! Harness for the end-to-end tests: builds and starts the real daemon binaries
//! (`generator-node`, `viz-node`, `tuner-node` and the `insitu` CLI) on 127.0.0.1 with ephemeral ports,
//! reads the address each prints, stops them with SIGTERM, and finds the shared data.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::OnceLock;
use std::time::Duration;

pub mod browser;
pub mod drift;

/// The standard output of the command `what` (`out`), once it has succeeded.
///
/// # Panics
/// When it failed, with its standard error and output.
pub fn succeeded(what: &str, out: std::process::Output) -> String {
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{what} failed: {}\n{text}",
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

/// A loopback port nobody listens on right now (for a daemon that starts later).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The status code and body of an HTTP/1.1 response (code 0 when it is not one).
pub fn parse_http_response(bytes: &[u8]) -> (u16, String) {
    let text = String::from_utf8_lossy(bytes);
    let code = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text.split_once("\r\n\r\n").map_or("", |x| x.1).to_owned();
    (code, body)
}

/// The directory the workspace's binaries are built into (next to this test's `deps/`).
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> → target/<profile>
    exe.parent()
        .and_then(Path::parent)
        .expect("target dir")
        .to_owned()
}

/// Builds the daemon and CLI binaries and the C client library once per test process (a no-op
/// when they are fresh), with the same profile as this test.
///
/// In the dev profile this is `cargo test --workspace --no-run`: the very feature resolution of
/// `cargo test --workspace` (CI's command), so right after it nothing is rebuilt. A narrower
/// `cargo build -p …` resolves dependency features differently (dev-dependencies take part in
/// one and not the other) and would rebuild minutes of dependencies in CI. Benchmarks
/// (release) build just the binaries and the library.
pub fn ensure_built() {
    static BUILT: OnceLock<()> = OnceLock::new();
    BUILT.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let release = bin_dir().file_name().is_some_and(|n| n == "release");
        let mut cmd = Command::new(cargo);
        // What `cargo test` set for this test process describes this package, not the build:
        // some build scripts (ring's) rerun when such variables change, which rebuilt
        // dependencies here.
        for (k, _) in std::env::vars_os().filter_map(|(k, v)| Some((k.into_string().ok()?, v))) {
            if k.starts_with("CARGO_PKG_")
                || k.starts_with("CARGO_BIN_EXE_")
                || matches!(
                    k.as_str(),
                    "CARGO_MANIFEST_DIR"
                        | "CARGO_MANIFEST_PATH"
                        | "CARGO_CRATE_NAME"
                        | "CARGO_PRIMARY_PACKAGE"
                        | "CARGO_TARGET_TMPDIR"
                        | "OUT_DIR"
                )
            {
                cmd.env_remove(k);
            }
        }
        if release {
            cmd.args([
                "build",
                "--release",
                "--bins",
                "--lib",
                "-p",
                "insitu-generator-node",
                "-p",
                "insitu-viz-node",
                "-p",
                "insitu-cli",
                "-p",
                "insitu-tuner-node",
                "-p",
                "insitu-client-c",
            ]);
        } else {
            cmd.args(["test", "--workspace", "--no-run"]);
        }
        let status = cmd
            .status()
            .expect("running cargo build for the daemon binaries");
        assert!(status.success(), "building the daemon binaries failed");
    });
}

/// A binary of the workspace.
pub fn bin(name: &str) -> PathBuf {
    ensure_built();
    bin_dir().join(name)
}

/// How long [`Daemon::terminate`] waits for a daemon to exit after SIGTERM (its graceful
/// shutdown drains queued steps, which can take a while on a loaded machine).
pub const STOP_WITHIN: Duration = Duration::from_secs(120);

/// A daemon process; killed on drop if still running.
pub struct Daemon {
    /// The process.
    pub child: Child,
    /// The address it printed.
    pub addr: String,
    stdout: Option<BufReader<ChildStdout>>,
    /// Its stderr log file.
    pub log: PathBuf,
}

impl Daemon {
    /// Starts `name` with `args` (and `envs`), logging stderr to `log_dir/name.log`, and waits
    /// for its `listening on ADDR` line.
    pub fn start(name: &str, args: &[&str], envs: &[(&str, &str)], log_dir: &Path) -> Self {
        let mut cmd = Command::new(bin(name));
        cmd.args(args).env_remove("INSITU_TOKEN");
        for (k, v) in envs {
            cmd.env(k, v);
        }
        Self::spawn(name, cmd, log_dir)
    }

    /// Starts `cmd` (a daemon `name`, perhaps under a wrapper such as `setpriv`; its
    /// environment as `cmd` sets it), its stderr into `log_dir`, and waits for its
    /// `listening on` line.
    pub fn spawn(name: &str, mut cmd: Command, log_dir: &Path) -> Self {
        let log = log_dir.join(format!("{name}-{}.log", std::process::id()));
        let log_file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log)
            .unwrap();
        cmd.stdout(Stdio::piped()).stderr(log_file);
        let mut child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("starting {name}: {e}"));
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        let mut line = String::new();
        stdout.read_line(&mut line).unwrap();
        let Some(addr) = line.trim().strip_prefix("listening on ") else {
            let _ = child.kill();
            panic!(
                "{name} did not start: printed {line:?}; log:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
        };
        Self {
            addr: addr.to_owned(),
            child,
            stdout: Some(stdout),
            log,
        }
    }

    /// The next line it prints after `listening on` (e.g. the web viewer's URL), trimmed;
    /// empty at the end of its output.
    pub fn read_line(&mut self) -> String {
        let mut line = String::new();
        if let Some(s) = self.stdout.as_mut() {
            let _ = s.read_line(&mut line);
        }
        line.trim().to_owned()
    }

    /// Sends SIGTERM, waits, and returns the rest of its stdout (e.g. the summary).
    ///
    /// # Panics
    /// When it has not exited [`STOP_WITHIN`] after the signal (it is then killed, and the
    /// panic quotes its log): a daemon that ignores SIGTERM is a defect, not a slow test.
    pub fn terminate(mut self) -> String {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let reader = self.stdout.take().map(|mut s| {
            std::thread::spawn(move || {
                let mut rest = String::new();
                let _ = s.read_to_string(&mut rest);
                rest
            })
        });
        let deadline = std::time::Instant::now() + STOP_WITHIN;
        while matches!(self.child.try_wait(), Ok(None)) {
            if std::time::Instant::now() > deadline {
                let _ = self.child.kill();
                let _ = self.child.wait();
                panic!(
                    "pid {} did not stop within {} s of SIGTERM; log:\n{}",
                    self.child.id(),
                    STOP_WITHIN.as_secs(),
                    std::fs::read_to_string(&self.log).unwrap_or_default()
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        reader.and_then(|r| r.join().ok()).unwrap_or_default()
    }

    /// Sends `signal` (e.g. `STOP`, `CONT`) to the process with `kill`.
    pub fn signal(&self, signal: &str) {
        let ok = Command::new("kill")
            .args([&format!("-{signal}"), &self.child.id().to_string()])
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "kill -{signal} failed");
    }

    /// The process's peak resident memory so far (`VmHWM`), MiB (0 once it has exited).
    pub fn peak_rss_mib(&self) -> f64 {
        self.proc_status_mib("VmHWM:")
    }

    /// The process's resident memory now (`VmRSS`), MiB (0 once it has exited).
    pub fn rss_mib(&self) -> f64 {
        self.proc_status_mib("VmRSS:")
    }

    /// The process's minor page faults so far (`minflt` in `/proc/PID/stat`; each one a page
    /// the kernel handed out, zeroed, on first touch); 0 once it has exited.
    pub fn minor_faults(&self) -> u64 {
        let stat =
            std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).unwrap_or_default();
        // Fields after the command name (which may hold spaces) start at `state`, field 3;
        // `minflt` is field 10.
        stat.rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().nth(10 - 3))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    }

    fn proc_status_mib(&self, field: &str) -> f64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id()))
            .unwrap_or_default();
        status
            .lines()
            .find_map(|l| l.strip_prefix(field))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
            .map_or(0.0, |kb| kb / 1024.0)
    }

    /// Kills it at once (SIGKILL), as a crash would.
    pub fn kill(mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts a viz-node recording into `dir` on `listen`, with `extra` flags, logs in `logs`.
pub fn start_viz(dir: &Path, listen: &str, extra: &[&str], logs: &Path) -> Daemon {
    let mut args = vec!["--listen", listen, "--recording-dir"];
    let dir = dir.to_string_lossy().into_owned();
    args.push(&dir);
    args.extend_from_slice(extra);
    Daemon::start("viz-node", &args, &[], logs)
}

pub use insitu_testenv::{data_file, tf_file};

/// The ocean series (180×90×19 f32, 12 monthly steps, NaN land; docs/data.md).
pub const OCEAN: &str = "ocean_temp_ts_180x90x19x12_float32.raw";

/// The ocean series' path, or `None` where it is in none of the data folders (the test skips
/// and the binary says so when it exits; `insitu_testenv`).
pub fn ocean() -> Option<PathBuf> {
    data_file(OCEAN)
}

/// Whether `insitu` finds a GPU adapter (`--backend gpu` on a tiny render); `None` (the test
/// skips; `insitu_testenv`) where it finds none.
pub fn gpu_adapter() -> Option<()> {
    let png = std::env::temp_dir().join(format!("insitu-gpu-probe-{}.png", std::process::id()));
    let out = Command::new(bin("insitu"))
        .args(["render", "--backend", "gpu", "--size", "16", "--out"])
        .arg(&png)
        .output()
        .ok()?;
    let _ = std::fs::remove_file(&png);
    let err = String::from_utf8_lossy(&out.stderr);
    if err.contains("no GPU adapter found") {
        return insitu_testenv::skip(insitu_testenv::Need::Gpu, &err);
    }
    Some(())
}

/// A current-thread runtime for async client calls inside a test.
pub fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// Waits up to `secs` for `pred`, polling every 50 ms.
pub fn wait_until(secs: f64, mut pred: impl FnMut() -> bool) -> bool {
    let deadline = std::time::Instant::now() + Duration::from_secs_f64(secs);
    while std::time::Instant::now() < deadline {
        if pred() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    pred()
}

/// The C client library (`libinsitu.a`, built with this test's profile) and its header
/// directory, for compiling C programs against it.
pub fn c_client() -> (PathBuf, PathBuf) {
    ensure_built();
    let include = Path::new(env!("CARGO_MANIFEST_DIR")).join("../client-c/include");
    // `deps/`: where both `cargo test --no-run` and `cargo build` put it (only the latter
    // also copies it up a level).
    (bin_dir().join("deps").join("libinsitu.a"), include)
}

/// Compiles the C program `source` (relative to the repository root) with `compiler` (`cc`,
/// `mpicc`) against the C client into `exe`, with `-O2` and `flags`; panics with the
/// compiler's messages when it fails.
pub fn build_c(compiler: &Path, source: &str, exe: &Path, flags: &[&str]) {
    let (_, include) = c_client();
    let mut all = flags.to_vec();
    let include = include.to_string_lossy().into_owned();
    all.extend(["-I", &include]);
    compile(compiler, &[source], exe, &all);
}

/// Compiles the Fortran `sources` (relative to the repository root; modules first) with
/// `compiler` (`gfortran`, `mpifort`) against the C client into `exe`, with `-O2` and `flags`,
/// the modules' `.mod` files beside `exe`; panics with the compiler's messages when it fails.
pub fn build_fortran(compiler: &Path, sources: &[&str], exe: &Path, flags: &[&str]) {
    let modules = exe
        .parent()
        .unwrap_or(Path::new("."))
        .to_string_lossy()
        .into_owned();
    let mut all = flags.to_vec();
    all.extend(["-J", &modules]);
    compile(compiler, sources, exe, &all);
}

/// `compiler -O2 flags -o exe sources libinsitu.a -lpthread -ldl -lm`, or a panic with the
/// compiler's messages.
fn compile(compiler: &Path, sources: &[&str], exe: &Path, flags: &[&str]) {
    let (lib, _) = c_client();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let out = Command::new(compiler)
        .arg("-O2")
        .args(flags)
        .arg("-o")
        .arg(exe)
        .args(sources.iter().map(|s| root.join(s)))
        .arg(&lib)
        .args(["-lpthread", "-ldl", "-lm"])
        .output()
        .unwrap_or_else(|e| panic!("running {}: {e}", compiler.display()));
    assert!(
        out.status.success(),
        "{} {sources:?}: {}",
        compiler.display(),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The path of the Open MPI program `tool` on `PATH`, or `None` (the test skips;
/// `insitu_testenv`).
pub fn mpi_tool(tool: &str) -> Option<PathBuf> {
    insitu_testenv::tool(tool, insitu_testenv::Need::Mpi)
}
