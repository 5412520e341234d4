//! Each reader against files the reference libraries wrote (`scripts/write-fixtures.sh`: PyPI's
//! vtk, pynrrd, netCDF4, h5py and ADIOS2's own, XDMF beside): every variant's samples equal the source arrays bit for bit, every
//! step of a series, and the grid lands where the writer put it — where VTK's own reader puts
//! its bounds, for the formats VTK reads.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use insitu_readers::{open, Options};
use serde_json::Value;

#[test]
fn files_written_by_the_reference_libraries_read_as_their_source() {
    let Some(dir) = insitu_testenv::fixture_dir() else {
        return;
    };
    let manifest: Value =
        serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    let vec3 = |v: &Value| -> [f32; 3] { std::array::from_fn(|a| v[a].as_f64().unwrap() as f32) };
    // The manifest's grid, or the entry's own (a bare HDF5 file, cell data).
    let grid_of = |g: &Value| {
        let dims: [usize; 3] = std::array::from_fn(|a| g["dims"][a].as_u64().unwrap() as usize);
        (dims, vec3(&g["origin"]), vec3(&g["spacing"]))
    };
    let files = manifest["files"].as_array().unwrap();
    assert!(files.len() >= 30, "{} fixture entries", files.len());
    let mut skipped = Vec::new();
    for f in files {
        let name = f["file"].as_str().unwrap();
        // Files read through a C library need that reader's feature (`.ci/run` turns them on).
        if let Some(feature) = f["needs"].as_str() {
            let built = match feature {
                "netcdf4" => cfg!(feature = "netcdf4"),
                "hdf5" => cfg!(feature = "hdf5"),
                "adios2" => cfg!(feature = "adios2"),
                other => panic!("{name}: unknown feature {other}"),
            };
            if !built {
                skipped.push(format!("{name} ({feature})"));
                continue;
            }
        }
        let field = f["field"].as_str().map(str::to_owned);
        let what = format!("{name} {field:?}");
        let d = open(
            &dir.join(name),
            &Options {
                field,
                ..Options::default()
            },
        )
        .unwrap_or_else(|e| panic!("{what}: {e}"));
        let (dims, origin, spacing) = grid_of(if f["grid"].is_object() {
            &f["grid"]
        } else {
            &manifest["grid"]
        });
        assert_eq!(d.dims, dims, "{what}");
        assert_eq!(d.steps as u64, f["steps"].as_u64().unwrap(), "{what}");
        let close = |a: [f32; 3], b: [f32; 3]| (0..3).all(|i| (a[i] - b[i]).abs() <= 1e-6);
        assert!(
            close(d.origin.to_array(), origin),
            "{what}: origin {} vs {origin:?}",
            d.origin
        );
        assert_eq!(d.spacing.to_array(), spacing, "{what}: spacing");
        if let Some(b) = f["bounds"].as_array() {
            // VTK's bounds: [xmin, xmax, ymin, ymax, zmin, zmax].
            for a in 0..3 {
                let lo = d.origin[a];
                let hi = lo + (d.dims[a] - 1) as f32 * d.spacing[a];
                let (vlo, vhi) = (
                    b[2 * a].as_f64().unwrap() as f32,
                    b[2 * a + 1].as_f64().unwrap() as f32,
                );
                assert!(
                    (lo - vlo).abs() < 1e-5 && (hi - vhi).abs() < 1e-5,
                    "{what}: axis {a} [{lo}, {hi}] vs VTK's [{vlo}, {vhi}]"
                );
            }
        }
        let expect = open(
            &dir.join(f["expect"].as_str().unwrap()),
            &Options::default(),
        )
        .unwrap();
        assert_eq!(expect.steps, d.steps, "{what}");
        for t in 0..d.steps {
            let got = d
                .read_step(t)
                .unwrap_or_else(|e| panic!("{what} step {t}: {e}"));
            let want = expect.read_step(t).unwrap();
            let (got, want) = (got.data(), want.data());
            assert_eq!(got.len(), want.len(), "{what}");
            let first_diff = got
                .iter()
                .zip(want.iter())
                .position(|(a, b)| a.to_bits() != b.to_bits());
            assert!(
                first_diff.is_none(),
                "{what} step {t}: sample {first_diff:?} differs: {:?} vs {:?}",
                first_diff.map(|k| got[k]),
                first_diff.map(|k| want[k])
            );
        }
    }
    if !skipped.is_empty() {
        eprintln!(
            "skipped {} fixture entries whose reader is not built: {}",
            skipped.len(),
            skipped.join(", ")
        );
    }
}
