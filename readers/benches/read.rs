//! How fast each reader loads a large field, and what memory it takes to do it: an N³ f32 field
//! (N = 512 unless `INSITU_READ_BENCH_N` says otherwise) written as raw-appended `.vti`
//! (UInt64 header), NetCDF classic (big-endian), NRRD (raw) and our raw layout, and with the
//! features `netcdf4` and `hdf5` as netCDF-4 (contiguous, and deflated in z-planes) and HDF5
//! (contiguous), each read in a process of its own three times from the page cache. Prints per
//! format the best read's GB/s (file bytes, and the field's f32 bytes, over seconds) and the
//! process's peak RSS over the field's size.
//!
//! `cargo bench -p insitu-readers --bench read [--features netcdf4,hdf5]`

#![allow(clippy::unwrap_used, clippy::expect_used)] // a bench fails loudly

use std::io::Write;
use std::path::Path;
use std::time::Instant;

fn field(n: usize) -> Vec<f32> {
    (0..n * n * n)
        .map(|i| ((i % 1013) as f32 * 0.01).sin() * 100.0)
        .collect()
}

fn write_all(dir: &Path, n: usize) -> Vec<(&'static str, std::path::PathBuf)> {
    let v = field(n);
    let le: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    let be: Vec<u8> = v.iter().flat_map(|x| x.to_be_bytes()).collect();
    drop(v);
    let mut out = Vec::new();
    // Raw.
    let raw = dir.join(format!("field_{n}x{n}x{n}_float32.raw"));
    std::fs::write(&raw, &le).unwrap();
    out.push(("raw", raw));
    // VTK XML ImageData, appended raw.
    let vti = dir.join("field.vti");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&vti).unwrap());
    let m = n - 1;
    write!(f, r#"<?xml version="1.0"?>
<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" header_type="UInt64">
  <ImageData WholeExtent="0 {m} 0 {m} 0 {m}" Origin="0 0 0" Spacing="1 1 1">
    <Piece Extent="0 {m} 0 {m} 0 {m}">
      <PointData Scalars="f"><DataArray type="Float32" Name="f" format="appended" offset="0"/></PointData>
    </Piece>
  </ImageData>
  <AppendedData encoding="raw">
   _"#).unwrap();
    f.write_all(&(le.len() as u64).to_le_bytes()).unwrap();
    f.write_all(&le).unwrap();
    f.write_all(b"\n  </AppendedData>\n</VTKFile>\n").unwrap();
    drop(f);
    out.push(("vti", vti));
    // NRRD, raw.
    let nrrd = dir.join("field.nrrd");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&nrrd).unwrap());
    write!(f, "NRRD0004\ntype: float\ndimension: 3\nsizes: {n} {n} {n}\nendian: little\nencoding: raw\n\n").unwrap();
    f.write_all(&le).unwrap();
    drop(f);
    out.push(("nrrd", nrrd));
    // NetCDF classic: dims z, y, x; one float variable, no attributes.
    let nc = dir.join("field.nc");
    let mut h = b"CDF\x01".to_vec();
    h.extend_from_slice(&0u32.to_be_bytes());
    h.extend_from_slice(&0x0Au32.to_be_bytes());
    h.extend_from_slice(&3u32.to_be_bytes());
    for d in ["z", "y", "x"] {
        h.extend_from_slice(&1u32.to_be_bytes());
        h.extend_from_slice(d.as_bytes());
        h.extend_from_slice(&[0, 0, 0]);
        h.extend_from_slice(&(n as u32).to_be_bytes());
    }
    h.extend_from_slice(&[0; 8]);
    h.extend_from_slice(&0x0Bu32.to_be_bytes());
    h.extend_from_slice(&1u32.to_be_bytes());
    h.extend_from_slice(&1u32.to_be_bytes());
    h.extend_from_slice(b"f\0\0\0");
    h.extend_from_slice(&3u32.to_be_bytes());
    for id in 0..3u32 {
        h.extend_from_slice(&id.to_be_bytes());
    }
    h.extend_from_slice(&[0; 8]);
    h.extend_from_slice(&5u32.to_be_bytes());
    h.extend_from_slice(&(be.len() as u32).to_be_bytes());
    let begin = h.len() as u32 + 4;
    h.extend_from_slice(&begin.to_be_bytes());
    let mut f = std::io::BufWriter::new(std::fs::File::create(&nc).unwrap());
    f.write_all(&h).unwrap();
    f.write_all(&be).unwrap();
    drop(f);
    out.push(("nc", nc));
    let v = field(n);
    #[cfg(feature = "netcdf4")]
    for (name, deflate) in [("netCDF-4", false), ("netCDF-4 deflate", true)] {
        let path = dir.join(format!("field_{}.nc", usize::from(deflate)));
        let mut f = netcdf::create(&path).unwrap();
        for (d, len) in [("z", n), ("y", n), ("x", n)] {
            f.add_dimension(d, len).unwrap();
        }
        let mut var = f.add_variable::<f32>("f", &["z", "y", "x"]).unwrap();
        if deflate {
            var.set_chunking(&[1, n, n]).unwrap();
            var.set_compression(1, true).unwrap();
        }
        var.put_values(&v, ..).unwrap();
        drop(f);
        out.push((name, path));
    }
    #[cfg(feature = "hdf5")]
    {
        let path = dir.join("field.h5");
        let f = hdf5::File::create(&path).unwrap();
        let ds = f.new_dataset::<f32>().shape([n, n, n]).create("f").unwrap();
        ds.write_raw(&v).unwrap();
        drop(f);
        out.push(("HDF5", path));
    }
    drop(v);
    out
}

/// The process's peak resident set, bytes (Linux).
fn peak_rss() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--one") {
        let path = Path::new(&args[i + 1]);
        let mut best = f64::INFINITY;
        for _ in 0..3 {
            let t = Instant::now();
            let d = insitu_readers::open(path, &insitu_readers::Options::default()).unwrap();
            let v = d.read_step(0).unwrap();
            best = best.min(t.elapsed().as_secs_f64());
            assert_eq!(v.dims()[0], d.dims[0]);
        }
        println!("{best} {}", peak_rss());
        return;
    }
    let n: usize = std::env::var("INSITU_READ_BENCH_N")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(512);
    let dir = tempfile::tempdir().unwrap();
    let files = write_all(dir.path(), n);
    let field = (n * n * n * 4) as f64;
    println!(
        "read: {n}³ f32 ({:.0} MiB), best of 3 from the page cache, a process per format",
        field / (1 << 20) as f64
    );
    println!("| format | file GB/s | field GB/s | peak RSS / field |");
    println!("| --- | --- | --- | --- |");
    for (name, path) in files {
        let bytes = std::fs::metadata(&path).unwrap().len() as f64;
        let out = std::process::Command::new(&args[0])
            .arg("--one")
            .arg(&path)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let text = String::from_utf8_lossy(&out.stdout);
        let mut it = text.split_whitespace();
        let secs: f64 = it.next().unwrap().parse().unwrap();
        let rss: f64 = it.next().unwrap().parse().unwrap();
        println!(
            "| {name} | {:.2} | {:.2} | {:.2} |",
            bytes / secs / 1e9,
            field / secs / 1e9,
            rss / field
        );
    }
}
