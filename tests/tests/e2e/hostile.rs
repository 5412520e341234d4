//! Hostile files given to the real `insitu` binary: each is refused with an error that names
//! the file and the problem, the process exits 1 (never aborts), and a file that is not a
//! regular one never blocks it.

use insitu_e2e::bin;
use std::io::Write;
use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

/// `insitu render --volume path` with `env`, run by `sh` under `limits` (`ulimit` options).
fn render(path: &Path, limits: &str, env: &[(&str, &str)], out: &Path) -> Output {
    let script = format!("{limits} exec \"$0\" render --volume \"$1\" --size 32 --out \"$2\"");
    let mut c = Command::new("sh");
    c.args(["-c", &script])
        .arg(bin("insitu"))
        .arg(path)
        .arg(out)
        .env_remove("INSITU_READ_LIMIT");
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

fn refused(out: &Output, words: &[&str]) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(1), "{err}");
    for w in words {
        assert!(err.contains(w), "{err:?} lacks {w:?}");
    }
    assert!(
        !err.contains("panicked") && !err.contains("backtrace"),
        "{err}"
    );
    err
}

/// An NRRD whose 8 MiB of gzip (8192 members of 1 MiB of zeros) decode to the 2048³ bytes
/// its header claims: the probe's gzip bomb.
fn bomb(dir: &Path) -> std::path::PathBuf {
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    gz.write_all(&vec![0u8; 1 << 20]).unwrap();
    let member = gz.finish().unwrap();
    let mut file =
        b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2048 2048 2048\nencoding: gzip\n\n".to_vec();
    file.extend_from_slice(&member.repeat(8192));
    let path = dir.join("bomb.nrrd");
    std::fs::write(&path, file).unwrap();
    path
}

#[test]
fn a_gzip_bomb_is_refused_by_the_read_limit_or_the_allocator_not_an_abort() {
    let tmp = tempfile::tempdir().unwrap();
    let path = bomb(tmp.path());
    let png = tmp.path().join("out.png");
    bin("insitu"); // built before the clock starts
                   // Under a 4 GiB address space the default limit is 2 GiB: refused before decoding.
    let t = Instant::now();
    let out = render(&path, "ulimit -v 4194304;", &[], &png);
    refused(
        &out,
        &[
            "bomb.nrrd",
            "8.0 GiB of memory",
            "read limit of 2.0 GiB",
            "INSITU_READ_LIMIT",
        ],
    );
    assert!(t.elapsed() < Duration::from_secs(10), "{:?}", t.elapsed());
    // The limit raised past what the process may have: the allocation fails, and says so.
    let out = render(
        &path,
        "ulimit -v 4194304;",
        &[("INSITU_READ_LIMIT", "16G")],
        &png,
    );
    refused(&out, &["bomb.nrrd", "out of memory"]);
    // A limit that is not a size is named.
    let out = render(&path, "", &[("INSITU_READ_LIMIT", "lots")], &png);
    refused(&out, &["INSITU_READ_LIMIT=\"lots\""]);
    assert!(!png.exists());
}

#[test]
fn a_cut_short_vti_and_a_fifo_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let png = tmp.path().join("out.png");
    // The probe's file: an appended block whose count says 32 bytes with 10 following.
    let mut vti = br#"<?xml version="1.0"?>
<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt32">
  <ImageData WholeExtent="0 1 0 1 0 1" Origin="0 0 0" Spacing="1 1 1">
    <Piece Extent="0 1 0 1 0 1">
      <PointData Scalars="v">
        <DataArray type="Float32" Name="v" format="appended" offset="0"/>
      </PointData>
    </Piece>
  </ImageData>
  <AppendedData encoding="raw">
   _"#
    .to_vec();
    vti.extend_from_slice(&32u32.to_le_bytes());
    vti.extend_from_slice(&[7u8; 10]);
    vti.extend_from_slice(b"\n  </AppendedData>\n</VTKFile>\n");
    let path = tmp.path().join("cut.vti");
    std::fs::write(&path, &vti).unwrap();
    refused(&render(&path, "", &[], &png), &["cut.vti", "truncated"]);
    // A detached NRRD whose data file is a FIFO nobody writes: refused at once.
    let fifo = tmp.path().join("data.raw");
    assert!(Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap()
        .success());
    let nhdr = tmp.path().join("f.nhdr");
    std::fs::write(
        &nhdr,
        "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\ndata file: data.raw\n",
    )
    .unwrap();
    bin("insitu");
    let t = Instant::now();
    refused(&render(&nhdr, "", &[], &png), &["data.raw", "FIFO"]);
    assert!(t.elapsed() < Duration::from_secs(10), "{:?}", t.elapsed());
    assert!(!png.exists());
}
