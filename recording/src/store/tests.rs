//! The recording's store: its index across reopens and crashes, and damaged or legacy files.

use super::*;
use insitu_core::backend::TimeSource;
use insitu_core::evaluate::Sizing;
use insitu_core::vdi::codec::Codec;

fn entry(step: u64) -> Entry {
    Entry {
        resolution: 4,
        gamma: 0.5,
        codec: Some(Codec::Zstd),
        ..Entry::empty(step, 0)
    }
}

#[test]
fn the_index_survives_a_reopen_and_names_only_complete_files() {
    let dir = tempfile::tempdir().unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    rec.store_vdi(entry(3), b"vdi bytes").unwrap();
    // A retry with the same bytes is fine; other bytes for the same (step, rank) are not.
    assert!(!rec.store_vdi(entry(3), b"vdi bytes").unwrap().1);
    assert!(matches!(
        rec.store_vdi(entry(3), b"other bytes"),
        Err(StoreError::AlreadyExists {
            step: 3,
            rank: 0,
            ..
        })
    ));
    let refs = References {
        camera: Camera::default_for_box(&insitu_core::volume::Aabb {
            min: glam_vec(0.0),
            max: glam_vec(1.0),
        }),
        view_angles_deg: vec![0.0, 30.0],
        frames: vec![Image::new(2, 3), Image::new(2, 3)],
        opacity: Some(vec![vec![0.5; 6], vec![1.0; 6]]),
    };
    rec.store_references(3, 0, &refs).unwrap();
    rec.set_quality(
        3,
        0,
        Quality {
            q_db: Db(f64::INFINITY),
            view_q_db: vec![Db(f64::INFINITY), Db(40.0)],
            view_mse: vec![0.0, 1e-4],
            ssim: None,
        },
    )
    .unwrap();
    drop(rec);
    let rec = Recording::open(dir.path()).unwrap();
    let e = rec.entry(3, 0).unwrap();
    assert_eq!(e.quality.unwrap().q_db, Db(f64::INFINITY));
    assert_eq!(
        References::read(&dir.path().join(e.references.unwrap())).unwrap(),
        refs
    );
    assert_eq!(
        std::fs::read(dir.path().join(e.vdi.unwrap())).unwrap(),
        b"vdi bytes"
    );
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|d| d.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().all(|n| !n.starts_with(".tmp-")), "{names:?}");
}

#[test]
fn a_corrupt_index_is_refused_not_replaced() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(LEGACY_INDEX), b"{ half").unwrap();
    let e = Recording::open(dir.path()).err().unwrap().to_string();
    assert!(e.contains("index.json"), "{e}");
    assert_eq!(
        std::fs::read(dir.path().join(LEGACY_INDEX)).unwrap(),
        b"{ half"
    );
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join(INDEX_DB),
        b"not a database at all, not even close",
    )
    .unwrap();
    let e = Recording::open(dir.path()).err().unwrap().to_string();
    assert!(e.contains("index.sqlite"), "{e}");
}

#[test]
fn payloads_without_an_index_are_not_orphaned_and_a_crash_is_tidied() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(vdi_name(1, 0)), b"x").unwrap();
    let e = Recording::open(dir.path()).err().unwrap().to_string();
    assert!(e.contains("1 VDI or reference files"), "{e}");

    let dir = tempfile::tempdir().unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    rec.store_vdi(entry(1), b"one").unwrap();
    rec.store_vdi(entry(2), b"two").unwrap();
    std::fs::write(dir.path().join(".tmp-abc"), b"half").unwrap();
    std::fs::write(dir.path().join(vdi_name(9, 0)), b"no row").unwrap();
    std::fs::remove_file(dir.path().join(vdi_name(2, 0))).unwrap();
    drop(rec);
    let rec = Recording::open(dir.path()).unwrap();
    // What is left to do is read without touching a file (a write in flight keeps its
    // temporary file); the same as `recover` finds.
    let todo = rec.left_to_do();
    assert!(dir.path().join(".tmp-abc").exists());
    let r = rec.recover().unwrap();
    assert_eq!(
        (&todo.unscored, &todo.uncomposed),
        (&r.unscored, &r.uncomposed)
    );
    assert!(todo.temp_removed.is_empty() && todo.files_without_rows.is_empty());
    assert_eq!(r.temp_removed, [".tmp-abc"]);
    assert_eq!(r.files_without_rows, [vdi_name(9, 0)]);
    assert_eq!(r.rows_without_files, [vdi_name(2, 0)]);
    assert!(!dir.path().join(".tmp-abc").exists());
}

/// Reading a recording no viz-node is writing leaves no file beside its index (it may be
/// on read-only media); one being written is read through its log, newest rows included.
#[test]
fn reading_a_recording_writes_nothing_and_sees_the_newest_rows() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("a dir with spaces & 100%");
    let rec = Recording::open(&dir).unwrap();
    rec.store_vdi(entry(1), b"one").unwrap();
    // Being written: the log holds the row.
    let (rows, _) = crate::index::read(&dir).unwrap();
    assert_eq!(rows.len(), 1);
    rec.store_vdi(entry(2), b"two").unwrap();
    assert_eq!(crate::index::read(&dir).unwrap().0.len(), 2);
    drop(rec);
    let beside = |dir: &Path| {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|d| d.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with(INDEX_DB))
            .collect();
        names.sort();
        names
    };
    assert_eq!(beside(&dir), [INDEX_DB]);
    let (rows, _) = crate::index::read(&dir).unwrap();
    assert_eq!(rows.len(), 2);
    assert_eq!(
        beside(&dir),
        [INDEX_DB],
        "reading left files beside the index"
    );
}

/// A row naming a file that is not its own (an absolute path, `../`, another step's file)
/// makes nothing read it: the name is dropped when the index is read, and the step reads
/// as having no such file.
#[test]
fn an_index_row_never_names_a_file_outside_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    rec.store_vdi(entry(1), b"one").unwrap();
    rec.store_vdi(entry(2), b"two").unwrap();
    drop(rec);
    let db = IndexDb::open(dir.path(), true).unwrap();
    let mut e = db.entries().unwrap().remove(0);
    assert_eq!(e.vdi.as_deref(), Some(vdi_name(1, 0).as_str()));
    for outside in ["/etc/passwd", "../other/step_00000001_rank_0000.vdi"] {
        e.vdi = Some(outside.into());
        e.references = Some(vdi_name(2, 0));
        db.put_entry(&e).unwrap();
        let read = db.entries().unwrap().remove(0);
        assert_eq!((read.step, read.vdi, read.references), (1, None, None));
    }
    drop(db);
    let rec = Recording::open(dir.path()).unwrap();
    assert_eq!(rec.entry(1, 0).unwrap().vdi, None);
    assert_eq!(
        rec.entry(2, 0).unwrap().vdi.as_deref(),
        Some(vdi_name(2, 0).as_str())
    );
}

/// An index emptied (truncated to 0 bytes) beside stored steps is refused like a missing
/// one, and the stored files stay as they were.
#[test]
fn an_emptied_index_beside_stored_steps_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    rec.store_vdi(entry(1), b"one").unwrap();
    drop(rec);
    for aside in ["-wal", "-shm"] {
        let _ = std::fs::remove_file(dir.path().join(format!("{INDEX_DB}{aside}")));
    }
    std::fs::write(dir.path().join(INDEX_DB), b"").unwrap();
    let e = Recording::open(dir.path()).err().unwrap().to_string();
    assert!(e.contains("missing or empty") && e.contains("1 VDI"), "{e}");
    assert_eq!(
        std::fs::read(dir.path().join(vdi_name(1, 0))).unwrap(),
        b"one"
    );
    // An empty index with no stored steps beside it is a new recording.
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(INDEX_DB), b"").unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    rec.store_vdi(entry(1), b"one").unwrap();
}

#[test]
fn a_legacy_json_index_is_imported_once() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(vdi_name(4, 0)), b"v").unwrap();
    let e = Entry {
        vdi: Some(vdi_name(4, 0)),
        ..entry(4)
    };
    let json = serde_json::json!({"version": 1, "entries": [e]});
    std::fs::write(dir.path().join(LEGACY_INDEX), json.to_string()).unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    assert_eq!(rec.entry(4, 0), Some(e));
    assert!(dir.path().join("index.json.imported").exists());
    assert!(!dir.path().join(LEGACY_INDEX).exists());
}

/// Index rows written before the σ/τ record was shared and the codec typed read as they
/// were: an entry without a τ source (wall clock), a step without a compression time (0),
/// a codec the node did not name (`""`).
#[test]
fn rows_written_before_the_shared_record_still_read() {
    let mut e = serde_json::to_value(Entry {
        sizing: Sizing {
            sigma_bytes: 900,
            supersegments: 12,
            tau_secs: 0.4,
            tau_source: TimeSource::GpuTimestamps,
            tau_compress_secs: 0.05,
        },
        ..entry(5)
    })
    .unwrap();
    assert_eq!(e["sigma_bytes"], 900);
    assert_eq!(e["tau_source"], "gpu-timestamps");
    assert_eq!(e["codec"], "zstd");
    e.as_object_mut().unwrap().remove("tau_source");
    let old: Entry = serde_json::from_value(e.clone()).unwrap();
    assert_eq!(old.sizing.tau_source, TimeSource::WallClock);
    assert_eq!(
        (old.sizing.sigma_bytes, old.sizing.tau_compress_secs),
        (900, 0.05)
    );
    assert_eq!(old.codec, Some(Codec::Zstd));
    // A codec the node did not name was stored as "".
    e["codec"] = "".into();
    let unnamed: Entry = serde_json::from_value(e.clone()).unwrap();
    assert_eq!(unnamed.codec, None);
    assert_eq!(serde_json::to_value(&unnamed).unwrap()["codec"], "");
    e["codec"] = "lzma".into();
    let err = serde_json::from_value::<Entry>(e).unwrap_err().to_string();
    assert!(err.contains("lzma"), "{err}");
    let step = serde_json::json!({"step": 5, "world_size": 2, "ranks": [0, 1], "missing": [],
        "vdi": null, "references": null, "sigma_bytes": 1800, "tau_secs": 0.4,
        "supersegments": 30, "resolution": 4, "gamma": 0.5, "pm_version": 1,
        "codec": "zstd", "quality": null, "error": null});
    let old: StepEntry = serde_json::from_value(step).unwrap();
    assert_eq!(
        old.sizing,
        Sizing {
            sigma_bytes: 1800,
            supersegments: 30,
            tau_secs: 0.4,
            ..Sizing::default()
        }
    );
}

#[test]
fn malformed_reference_bytes_are_refused() {
    let cam = Camera {
        eye: glam_vec(5.0),
        target: glam_vec(0.0),
        up: glam::Vec3::Y,
        fov_y_deg: 30.0,
    };
    assert!(References::from_bytes(cam, vec![0.0], (2, 2), false, &[0u8; 47]).is_err());
    assert!(References::from_bytes(cam, vec![0.0], (2, 2), true, &[0u8; 48]).is_err());
    assert!(References::from_bytes(cam, vec![0.0], (2, 2), true, &[0u8; 64]).is_ok());
    let nan: Vec<u8> = std::iter::repeat_n(f32::NAN.to_le_bytes(), 12)
        .flatten()
        .collect();
    assert!(References::from_bytes(cam, vec![0.0], (2, 2), false, &nan).is_err());
    assert!(References::from_bytes(cam, vec![], (2, 2), false, &[]).is_err());
}

/// A reference-frames file damaged within range (one float's low byte changed: still a
/// valid frame) is refused by its checksum, not served; a file of the format before the
/// checksum still reads.
#[test]
fn damaged_reference_frames_are_refused_by_their_checksum() {
    let cam = Camera {
        eye: glam_vec(5.0),
        target: glam_vec(0.0),
        up: glam::Vec3::Y,
        fov_y_deg: 30.0,
    };
    let frames: Vec<u8> = (0..12u32)
        .flat_map(|k| (k as f32 / 16.0).to_le_bytes())
        .collect();
    let refs = References::from_bytes(cam, vec![0.0], (2, 2), false, &frames).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.refs");
    let good = refs.to_file_bytes((7, Some(2)));
    std::fs::write(&path, &good).unwrap();
    assert_eq!(
        References::read_with_origin(&path).unwrap(),
        (refs.clone(), Some((7, Some(2))))
    );
    let mut damaged = good.clone();
    let at = damaged.len() - 4 - 8; // a frame float's low byte, before the checksum
    damaged[at] ^= 1;
    std::fs::write(&path, &damaged).unwrap();
    let e = References::read(&path).unwrap_err().to_string();
    assert!(
        e.contains("checksum mismatch") && e.contains("r.refs"),
        "{e}"
    );
    let mut v1 = good[..good.len() - 4].to_vec();
    v1[..8].copy_from_slice(REFS_MAGIC_V1);
    std::fs::write(&path, &v1).unwrap();
    assert_eq!(References::read(&path).unwrap(), refs);
}

fn glam_vec(v: f32) -> glam::Vec3 {
    glam::Vec3::splat(v)
}
