//! Each reader against files written here byte by byte from each format's specification:
//! the values read equal the values written (bit for bit for floats), origin and spacing
//! land where the format says, and every malformed file is refused with a message naming it.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use glam::Vec3;
use insitu_readers::{open, Options};
use std::io::Write;
use std::path::{Path, PathBuf};

/// A field of `dims` with distinct values, x fastest.
fn field(dims: [usize; 3]) -> Vec<f32> {
    (0..dims.iter().product::<usize>())
        .map(|i| (i as f32).mul_add(0.37, -3.0))
        .collect()
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

fn values(path: &Path, field: Option<&str>, t: usize) -> (insitu_readers::Dataset, Vec<f32>) {
    let d = open(
        path,
        &Options {
            field: field.map(str::to_owned),
            ..Options::default()
        },
    )
    .unwrap();
    let v = d.read_step(t).unwrap();
    let data = v.data().into_owned();
    (d, data)
}

fn refused(path: &Path, needle: &str) {
    let e = match open(path, &Options::default()) {
        Err(e) => e.to_string(),
        Ok(d) => match d.read_step(0) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("{} was read", path.display()),
        },
    };
    assert!(e.contains(needle), "{e:?} lacks {needle:?}");
    assert!(
        e.contains(&path.file_name().unwrap().to_string_lossy().into_owned()),
        "{e}"
    );
}

// ---------------------------------------------------------------- NetCDF classic

/// A NetCDF classic (CDF-1) file writer for the tests: fixed dimensions only.
struct Cdf {
    dims: Vec<(&'static str, u32)>,
    vars: Vec<CdfVar>,
}

struct CdfVar {
    name: &'static str,
    dims: Vec<usize>,
    /// (name, nc_type, big-endian values)
    attrs: Vec<(&'static str, u32, Vec<u8>)>,
    nc_type: u32,
    data: Vec<u8>,
}

fn name(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(&(s.len() as u32).to_be_bytes());
    out.extend_from_slice(s.as_bytes());
    out.resize(out.len().div_ceil(4) * 4, 0);
}

impl Cdf {
    fn bytes(&self) -> Vec<u8> {
        let header = |begins: &[u32]| {
            let mut h = b"CDF\x01".to_vec();
            h.extend_from_slice(&0u32.to_be_bytes());
            h.extend_from_slice(&0x0Au32.to_be_bytes());
            h.extend_from_slice(&(self.dims.len() as u32).to_be_bytes());
            for (n, len) in &self.dims {
                name(&mut h, n);
                h.extend_from_slice(&len.to_be_bytes());
            }
            h.extend_from_slice(&[0; 8]); // no global attributes
            h.extend_from_slice(&0x0Bu32.to_be_bytes());
            h.extend_from_slice(&(self.vars.len() as u32).to_be_bytes());
            for (v, begin) in self.vars.iter().zip(begins) {
                name(&mut h, v.name);
                h.extend_from_slice(&(v.dims.len() as u32).to_be_bytes());
                for d in &v.dims {
                    h.extend_from_slice(&(*d as u32).to_be_bytes());
                }
                if v.attrs.is_empty() {
                    h.extend_from_slice(&[0; 8]);
                } else {
                    h.extend_from_slice(&0x0Cu32.to_be_bytes());
                    h.extend_from_slice(&(v.attrs.len() as u32).to_be_bytes());
                    for (n, t, vals) in &v.attrs {
                        name(&mut h, n);
                        h.extend_from_slice(&t.to_be_bytes());
                        let size = match t {
                            1 | 2 => 1,
                            3 => 2,
                            6 => 8,
                            _ => 4,
                        };
                        h.extend_from_slice(&((vals.len() / size) as u32).to_be_bytes());
                        h.extend_from_slice(vals);
                        h.resize(h.len().div_ceil(4) * 4, 0);
                    }
                }
                h.extend_from_slice(&v.nc_type.to_be_bytes());
                h.extend_from_slice(&(v.data.len().div_ceil(4) as u32 * 4).to_be_bytes());
                h.extend_from_slice(&begin.to_be_bytes());
            }
            h
        };
        let start = header(&vec![0; self.vars.len()]).len() as u32;
        let mut begins = Vec::new();
        let mut at = start;
        for v in &self.vars {
            begins.push(at);
            at += v.data.len().div_ceil(4) as u32 * 4;
        }
        let mut out = header(&begins);
        for v in &self.vars {
            out.extend_from_slice(&v.data);
            out.resize(out.len().div_ceil(4) * 4, 0);
        }
        out
    }
}

fn be_f32(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_be_bytes()).collect()
}

fn be_f64(v: &[f64]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_be_bytes()).collect()
}

/// TEMP(time 2, depth 3, lat 4, lon 5): short data with a scale, an offset and a fill value;
/// lon even from 10 by 2, lat even from -30 by 5, depth uneven (0, 10, 30).
fn ocean_like(dir: &Path) -> (PathBuf, Vec<i16>) {
    let n = 2 * 3 * 4 * 5;
    let mut raw: Vec<i16> = (0..n).map(|i| i as i16 * 7 - 100).collect();
    raw[3] = -32767; // the fill value
    let coord = |name: &'static str, dim: usize, v: &[f64]| CdfVar {
        name,
        dims: vec![dim],
        attrs: vec![("units", 2, b"m".to_vec())],
        nc_type: 6,
        data: be_f64(v),
    };
    let cdf = Cdf {
        dims: vec![("time", 2), ("depth", 3), ("lat", 4), ("lon", 5)],
        vars: vec![
            coord("lon", 3, &[10.0, 12.0, 14.0, 16.0, 18.0]),
            coord("lat", 2, &[-30.0, -25.0, -20.0, -15.0]),
            coord("depth", 1, &[0.0, 10.0, 30.0]),
            CdfVar {
                name: "TEMP",
                dims: vec![0, 1, 2, 3],
                attrs: vec![
                    ("scale_factor", 5, be_f32(&[0.5])),
                    ("add_offset", 5, be_f32(&[20.0])),
                    ("_FillValue", 3, (-32767i16).to_be_bytes().to_vec()),
                ],
                nc_type: 3,
                data: raw.iter().flat_map(|v| v.to_be_bytes()).collect(),
            },
        ],
    };
    (write(dir, "ocean.nc", &cdf.bytes()), raw)
}

#[test]
fn netcdf_applies_cf_attributes_and_places_the_axes() {
    let dir = tempfile::tempdir().unwrap();
    let (path, raw) = ocean_like(dir.path());
    let opts = Options {
        uneven: insitu_readers::Uneven::Index,
        ..Options::default()
    };
    let d = open(&path, &opts).unwrap();
    assert_eq!((d.dims, d.steps, d.field.as_str()), ([5, 4, 3], 2, "TEMP"));
    assert_eq!(d.spacing, Vec3::new(2.0, 5.0, 1.0));
    assert_eq!(d.origin, Vec3::new(10.0, -30.0, 0.0));
    assert!(
        d.notes.iter().any(|n| n.contains("depth is uneven")),
        "{:?}",
        d.notes
    );
    for t in 0..2 {
        let got = d.read_step(t).unwrap().data().into_owned();
        for (k, g) in got.iter().enumerate() {
            let r = raw[t * 60 + k];
            if r == -32767 {
                assert!(g.is_nan());
            } else {
                assert_eq!(*g, (f64::from(r) * 0.5 + 20.0) as f32, "t {t} sample {k}");
            }
        }
    }
    // Resampled: depth 0..30 at its smallest gap (10) gives 4 levels; level 2 (z = 20) lies
    // halfway between the file's levels 1 (10 m) and 2 (30 m).
    let d = open(&path, &Options::default()).unwrap();
    assert_eq!((d.dims, d.spacing.z), ([5, 4, 4], 10.0));
    assert!(
        d.notes
            .iter()
            .any(|n| n.contains("resampled linearly from 3 levels to 4")),
        "{:?}",
        d.notes
    );
    let got = d.read_step(1).unwrap().data().into_owned();
    let file = |z: usize, k: usize| (f64::from(raw[60 + z * 20 + k]) * 0.5 + 20.0) as f32;
    for k in 4..20 {
        assert_eq!(got[k], file(0, k), "a level is kept as it is");
        assert_eq!(got[20 + k], file(1, k));
        let mid = file(1, k) + (file(2, k) - file(1, k)) * 0.5;
        assert!((got[40 + k] - mid).abs() < 1e-4, "{} vs {mid}", got[40 + k]);
        assert_eq!(got[60 + k], file(2, k));
    }
}

#[test]
fn netcdf_refuses_what_it_cannot_read_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let (path, _) = ocean_like(dir.path());
    let bytes = std::fs::read(&path).unwrap();
    let e = open(
        &path,
        &Options {
            field: Some("SALT".into()),
            ..Options::default()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("no variable \"SALT\"") && e.contains("TEMP"),
        "{e}"
    );
    let e = open(
        &path,
        &Options {
            field: Some("lon".into()),
            ..Options::default()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("1 dimensions"), "{e}");
    refused(
        &write(dir.path(), "cut.nc", &bytes[..bytes.len() - 10]),
        "truncated",
    );
    refused(&write(dir.path(), "head.nc", &bytes[..40]), "truncated");
    refused(
        &write(dir.path(), "hdf.nc", b"\x89HDF\r\n\x1a\n...."),
        "netCDF-4",
    );
    refused(
        &write(dir.path(), "junk.nc", b"JUNKJUNK"),
        "not a NetCDF file",
    );
}

/// The Debian `ferret-datasets` ocean atlas (classic NetCDF): its TEMP equals the shared raw
/// series cut from it, bit for bit, with the depth levels kept by index.
#[test]
fn the_ocean_atlas_temp_equals_the_raw_series() {
    let nc = Path::new("/usr/share/ferret-vis/data/ocean_atlas_subset.nc");
    let Some(nc) = insitu_testenv::file(nc, insitu_testenv::Need::Data) else {
        return;
    };
    let Some(raw) = insitu_testenv::data_file("ocean_temp_ts_180x90x19x12_float32.raw") else {
        return;
    };
    let opts = Options {
        field: Some("TEMP".into()),
        uneven: insitu_readers::Uneven::Index,
    };
    let d = open(&nc, &opts).unwrap();
    assert_eq!((d.dims, d.steps), ([180, 90, 19], 12));
    let series = open(&raw, &Options::default()).unwrap();
    for t in 0..12 {
        let a = d.read_step(t).unwrap().data().into_owned();
        let b = series.read_step(t).unwrap().data().into_owned();
        let same = a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same && a.len() == b.len(), "step {t} differs");
    }
}

// ---------------------------------------------------------------- NRRD

#[test]
fn nrrd_attached_detached_gzip_and_big_endian_read_as_written() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [4, 3, 2];
    let v = field(dims);
    let le: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    let mut attached = b"NRRD0004\n# a comment\ntype: float\ndimension: 3\nsizes: 4 3 2\nendian: little\nencoding: raw\nspace dimension: 3\nspace directions: (0.5,0,0) (0,2,0) (0,0,3)\nspace origin: (1,-2,3.5)\n\n".to_vec();
    attached.extend_from_slice(&le);
    let (d, got) = values(&write(dir.path(), "a.nrrd", &attached), None, 0);
    assert_eq!(got, v);
    assert_eq!(
        (d.spacing, d.origin),
        (Vec3::new(0.5, 2.0, 3.0), Vec3::new(1.0, -2.0, 3.5))
    );
    // Detached, gzip, big-endian u16.
    let u: Vec<u16> = (0..24u16).map(|i| i * 1000).collect();
    let be: Vec<u8> = u.iter().flat_map(|x| x.to_be_bytes()).collect();
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    gz.write_all(&be).unwrap();
    write(dir.path(), "b.raw.gz", &gz.finish().unwrap());
    let nhdr = write(
        dir.path(),
        "b.nhdr",
        b"NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4 3 2\nendian: big\nencoding: gzip\nspacings: 1 1 2\ndata file: b.raw.gz\n",
    );
    let (d, got) = values(&nhdr, None, 0);
    assert_eq!(got, u.iter().map(|&x| f32::from(x)).collect::<Vec<_>>());
    assert_eq!(d.spacing, Vec3::new(1.0, 1.0, 2.0));
    // Refusals.
    let header = String::from_utf8_lossy(&attached[..attached.len() - le.len()]).into_owned();
    let with = |from: &str, to: &str| {
        let mut b = header.replace(from, to).into_bytes();
        b.extend_from_slice(&le);
        b
    };
    refused(
        &write(dir.path(), "rot.nrrd", &with("(0.5,0,0)", "(0.5,0.1,0)")),
        "not axis-aligned",
    );
    refused(
        &write(dir.path(), "d4.nrrd", &with("dimension: 3", "dimension: 4")),
        "dimension 4",
    );
    refused(
        &write(
            dir.path(),
            "txt.nrrd",
            &with("encoding: raw", "encoding: hex"),
        ),
        "encoding \"hex\"",
    );
    refused(
        &write(dir.path(), "cut.nrrd", &attached[..attached.len() - 4]),
        "bytes of samples",
    );
    refused(
        &write(dir.path(), "no.nrrd", b"P6\n4 4\n"),
        "not an NRRD file",
    );
}

/// A gzip stream of `members` concatenated members, each `member` zero bytes: what a
/// "gzip bomb" is, built cheaply (the reader takes concatenated members, as gzip does).
fn gzip_zeros(member: usize, members: usize) -> Vec<u8> {
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    gz.write_all(&vec![0u8; member]).unwrap();
    gz.finish().unwrap().repeat(members)
}

#[test]
fn nrrd_claims_are_checked_against_the_read_limit_and_what_is_there() {
    let dir = tempfile::tempdir().unwrap();
    // 16384³ bytes (4 TiB) claimed by 64 KiB of gzip: over any machine's read limit, refused
    // before a byte is decoded.
    let mut bomb =
        b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 16384 16384 16384\nencoding: gzip\n\n"
            .to_vec();
    bomb.extend_from_slice(&gzip_zeros(1 << 20, 64));
    refused(
        &write(dir.path(), "bomb.nrrd", &bomb),
        "4.0 TiB of memory, over the read limit",
    );
    // A gzip body holding less than its header claims ends as "early", not as a volume.
    let mut short =
        b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 64 64 64\nencoding: gzip\n\n".to_vec();
    short.extend_from_slice(&gzip_zeros(1000, 3));
    refused(&write(dir.path(), "short.nrrd", &short), "ends");
    // And one holding more is refused too.
    let mut long =
        b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 8 8 8\nencoding: gzip\n\n".to_vec();
    long.extend_from_slice(&gzip_zeros(512, 2));
    refused(&write(dir.path(), "long.nrrd", &long), "more than");
}

#[cfg(unix)]
#[test]
fn fifos_and_directories_are_refused_without_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("data.raw");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    assert!(made.unwrap().success(), "mkfifo (coreutils) failed");
    // A detached header whose data file is a FIFO: opening it would block for a writer.
    let nhdr = write(
        dir.path(),
        "f.nhdr",
        b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\nencoding: raw\ndata file: data.raw\n",
    );
    let e = open(&nhdr, &Options::default())
        .and_then(|d| d.read_step(0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("data.raw: a FIFO"), "{e}");
    let named = dir.path().join("f.vti");
    std::fs::rename(&fifo, &named).unwrap();
    refused(&named, "a FIFO");
    let sub = dir.path().join("d.nrrd");
    std::fs::create_dir(&sub).unwrap();
    refused(&sub, "a directory");
}

// ---------------------------------------------------------------- legacy VTK

#[test]
fn legacy_vtk_ascii_and_binary_with_several_arrays() {
    let dir = tempfile::tempdir().unwrap();
    let dims = [3, 2, 2];
    let v = field(dims);
    let head = "# vtk DataFile Version 3.0\ntest\n{FMT}\nDATASET STRUCTURED_POINTS\nDIMENSIONS 3 2 2\nORIGIN 1 2 3\nSPACING 0.5 0.5 2\nPOINT_DATA 12\n";
    let ascii = format!(
        "{}SCALARS first float 1\nLOOKUP_TABLE default\n{}\nSCALARS second double\nLOOKUP_TABLE default\n{}\n",
        head.replace("{FMT}", "ASCII"),
        v.iter().map(|x| format!("{x:?}")).collect::<Vec<_>>().join(" "),
        v.iter().map(|x| format!("{:?}", x * 2.0)).collect::<Vec<_>>().join("\n"),
    );
    let path = write(dir.path(), "a.vtk", ascii.as_bytes());
    let (d, got) = values(&path, None, 0);
    assert_eq!(got, v);
    assert_eq!(
        (d.origin, d.spacing),
        (Vec3::new(1.0, 2.0, 3.0), Vec3::new(0.5, 0.5, 2.0))
    );
    assert_eq!(d.fields, ["first", "second"]);
    let (_, got) = values(&path, Some("second"), 0);
    assert_eq!(got, v.iter().map(|x| x * 2.0).collect::<Vec<_>>());
    let mut bin = head.replace("{FMT}", "BINARY").into_bytes();
    bin.extend_from_slice(b"SCALARS s short\nLOOKUP_TABLE default\n");
    let s: Vec<i16> = (0..12).map(|i| i * 300 - 2000).collect();
    bin.extend(s.iter().flat_map(|x| x.to_be_bytes()));
    bin.push(b'\n');
    let (_, got) = values(&write(dir.path(), "b.vtk", &bin), None, 0);
    assert_eq!(got, s.iter().map(|&x| f32::from(x)).collect::<Vec<_>>());
    refused(
        &write(dir.path(), "cut.vtk", &bin[..bin.len() - 5]),
        "truncated",
    );
    refused(
        &write(
            dir.path(),
            "grid.vtk",
            ascii
                .replace("STRUCTURED_POINTS", "UNSTRUCTURED_GRID")
                .as_bytes(),
        ),
        "only DATASET STRUCTURED_POINTS",
    );
    let e = open(
        &path,
        &Options {
            field: Some("third".into()),
            ..Options::default()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("first, second"), "{e}");
}

// ---------------------------------------------------------------- VTK XML ImageData

fn vti(format_attrs: &str, array: &str, appended: Option<&[u8]>) -> Vec<u8> {
    let mut out = format!(
        r#"<?xml version="1.0"?>
<VTKFile type="ImageData" version="1.0" byte_order="LittleEndian" {format_attrs}>
  <ImageData WholeExtent="2 5 0 2 1 2" Origin="10 0 -1" Spacing="0.5 1 2" Direction="1 0 0 0 1 0 0 0 1">
    <Piece Extent="2 5 0 2 1 2">
      <PointData Scalars="rho">
        <DataArray type="Float32" Name="other" format="ascii">{}</DataArray>
        {array}
      </PointData>
    </Piece>
  </ImageData>
"#,
        "0 ".repeat(24)
    )
    .into_bytes();
    if let Some(data) = appended {
        out.extend_from_slice(b"  <AppendedData encoding=\"raw\">\n   _");
        out.extend_from_slice(data);
        out.extend_from_slice(b"\n  </AppendedData>\n");
    }
    out.extend_from_slice(b"</VTKFile>\n");
    out
}

#[test]
fn vti_ascii_base64_appended_and_zlib_read_as_written() {
    use base64::Engine as _;
    let dir = tempfile::tempdir().unwrap();
    let dims = [4, 3, 2];
    let v = field(dims);
    let le: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    let check = |name: &str, bytes: Vec<u8>| {
        let (d, got) = values(&write(dir.path(), name, &bytes), None, 0);
        assert_eq!(got, v, "{name}");
        assert_eq!(d.field, "rho", "{name}: the active scalars");
        assert_eq!(d.dims, dims);
        // VTK puts sample (i, j, k) of the extent at origin + (i, j, k) · spacing.
        assert_eq!(
            (d.origin, d.spacing),
            (Vec3::new(11.0, 0.0, 1.0), Vec3::new(0.5, 1.0, 2.0)),
            "{name}"
        );
    };
    let ascii = v
        .iter()
        .map(|x| format!("{x:?}"))
        .collect::<Vec<_>>()
        .join(" ");
    check(
        "ascii.vti",
        vti(
            "",
            &format!(r#"<DataArray type="Float32" Name="rho" format="ascii">{ascii}</DataArray>"#),
            None,
        ),
    );
    // Inline binary, UInt32 header, one base64 stream.
    let mut block = (le.len() as u32).to_le_bytes().to_vec();
    block.extend_from_slice(&le);
    let b64 = base64::engine::general_purpose::STANDARD.encode(&block);
    check(
        "binary.vti",
        vti(
            r#"header_type="UInt32""#,
            &format!(r#"<DataArray type="Float32" Name="rho" format="binary">{b64}</DataArray>"#),
            None,
        ),
    );
    // Appended raw, UInt64 header, zlib in two blocks of 64 and 32 bytes.
    let mut zblocks = Vec::new();
    for piece in le.chunks(64) {
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        z.write_all(piece).unwrap();
        zblocks.push(z.finish().unwrap());
    }
    let mut data = Vec::new();
    for w in [
        2u64,
        64,
        32,
        zblocks[0].len() as u64,
        zblocks[1].len() as u64,
    ] {
        data.extend_from_slice(&w.to_le_bytes());
    }
    zblocks.iter().for_each(|z| data.extend_from_slice(z));
    let attrs = r#"header_type="UInt64" compressor="vtkZLibDataCompressor""#;
    let array = r#"<DataArray type="Float32" Name="rho" format="appended" offset="0"/>"#;
    let file = vti(attrs, array, Some(&data));
    check("zlib.vti", file.clone());
    // Inline binary compressed: header and blocks base64-encoded apart, as VTK writes them.
    let (head, blocks) = data.split_at(5 * 8);
    let e = base64::engine::general_purpose::STANDARD;
    let text = format!("{}{}", e.encode(head), e.encode(blocks));
    check(
        "zlib64.vti",
        vti(
            attrs,
            &format!(r#"<DataArray type="Float32" Name="rho" format="binary">{text}</DataArray>"#),
            None,
        ),
    );
    // Refusals.
    refused(
        &write(dir.path(), "cut.vti", &file[..file.len() - 40]),
        "vti",
    );
    // An appended raw block whose count says 96 bytes with 80 following: the closing tags
    // after them are not samples.
    let plain = r#"<DataArray type="Float32" Name="rho" format="appended" offset="0"/>"#;
    let mut short = 96u32.to_le_bytes().to_vec();
    short.extend_from_slice(&le[..80]);
    refused(
        &write(dir.path(), "short.vti", &vti("", plain, Some(&short))),
        "truncated",
    );
    // Cut inside the data: no closing element at all.
    let mut whole = 96u32.to_le_bytes().to_vec();
    whole.extend_from_slice(&le);
    let full = vti("", plain, Some(&whole));
    check("raw.vti", full.clone());
    let cut = &full[..full.len() - 40];
    refused(&write(dir.path(), "cut-raw.vti", cut), "cut short");
    let rotated = String::from_utf8_lossy(&file).replace("1 0 0 0 1 0 0 0 1", "0 1 0 1 0 0 0 0 1");
    refused(
        &write(dir.path(), "rot.vti", rotated.as_bytes()),
        "axis-aligned",
    );
    let lz4 =
        String::from_utf8_lossy(&file).replace("vtkZLibDataCompressor", "vtkLZ4DataCompressor");
    refused(&write(dir.path(), "lz4.vti", lz4.as_bytes()), "only zlib");
    let e = open(
        &write(dir.path(), "f.vti", &file),
        &Options {
            field: Some("p".into()),
            ..Options::default()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("other, rho"), "{e}");
}

#[test]
fn an_unknown_extension_names_the_known_ones() {
    let dir = tempfile::tempdir().unwrap();
    refused(&write(dir.path(), "x.grib", b""), ".vti, .vtk, .h5");
}

/// A 3DCoRectMesh of 4×3×2 points at origin (1, 2, 3), spacing (0.5, 1, 2), with `attribute`.
fn xdmf(topology: &str, attribute: &str) -> Vec<u8> {
    format!(
        r#"<?xml version="1.0"?>
<Xdmf Version="3.0"><Domain><Grid Name="g" GridType="Uniform">
  <Topology TopologyType="{topology}" Dimensions="2 3 4"/>
  <Geometry GeometryType="ORIGIN_DXDYDZ">
    <DataItem Format="XML" Dimensions="3">3 2 1</DataItem>
    <DataItem Format="XML" Dimensions="3">2 1 0.5</DataItem>
  </Geometry>
  {attribute}
</Grid></Domain></Xdmf>"#
    )
    .into_bytes()
}

#[test]
fn xdmf_descriptions_are_checked_before_any_dataset_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let rho = r#"<Attribute Name="rho" Center="Node"><DataItem Format="HDF" Dimensions="2 3 4">missing.h5:/rho</DataItem></Attribute>"#;
    refused(
        &write(dir.path(), "rect.xmf", &xdmf("3DRectMesh", rho)),
        "only a uniform 3DCoRectMesh",
    );
    refused(
        &write(
            dir.path(),
            "binary.xmf",
            &xdmf("3DCoRectMesh", &rho.replace("HDF", "Binary")),
        ),
        "only HDF data items",
    );
    refused(
        &write(
            dir.path(),
            "vector.xmf",
            &xdmf(
                "3DCoRectMesh",
                &rho.replace("Center", "AttributeType=\"Vector\" Center"),
            ),
        ),
        "only scalar fields",
    );
    refused(
        &write(dir.path(), "cut.xmf", &xdmf("3DCoRectMesh", rho)[..200]),
        "XML",
    );
    let ok = write(dir.path(), "ok.xmf", &xdmf("3DCoRectMesh", rho));
    let e = open(
        &ok,
        &Options {
            field: Some("p".into()),
            ..Options::default()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("no attribute \"p\"; attributes here: rho"),
        "{e}"
    );
    // The description is sound; what is missing is the HDF5 file it names (or, without the
    // feature, the means to read it).
    let e = open(&ok, &Options::default()).unwrap_err().to_string();
    let want = if cfg!(feature = "hdf5") {
        "missing.h5: HDF5 cannot open it"
    } else {
        "--features hdf5"
    };
    assert!(e.contains(want), "{e}");
}

#[test]
fn files_that_need_a_c_library_name_the_feature_or_the_library_refuses_them() {
    let dir = tempfile::tempdir().unwrap();
    let h5 = write(dir.path(), "x.h5", b"\x89HDF\r\n\x1a\n....");
    let nc4 = write(dir.path(), "x.nc", b"\x89HDF\r\n\x1a\n....");
    // With the feature, the library itself refuses the cut file, and says so.
    refused(
        &h5,
        if cfg!(feature = "hdf5") {
            "HDF5 cannot open it"
        } else {
            "--features hdf5"
        },
    );
    refused(
        &nc4,
        if cfg!(feature = "netcdf4") {
            "netCDF-C cannot open this netCDF-4 file"
        } else {
            "--features netcdf4"
        },
    );
}
