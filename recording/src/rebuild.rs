//! Rebuilding a recording's index from its files (`insitu recover`), for an index that is
//! missing, emptied or damaged beside stored steps: the viz-node refuses to start on such a
//! recording rather than let a new index orphan the files and the next steps replace them.
//!
//! Every rank's VDI file carries its provenance (step, rank, world, `P_M` version, brick:
//! [`insitu_core::vdi::provenance`]) under its checksum, and every `.refs` file whose frames
//! it holds, so a row is made from the files alone: r, γ, the codec, the TF, σ (the file's
//! length) and the supersegments from the VDI itself. τ, a measurement the file does not
//! keep (a VDI made again must have the same bytes), is 0 in a rebuilt row: unknown. A file that cannot say where it belongs
//! (no provenance, a checksum that fails, a name its provenance contradicts) is left out and
//! listed, never guessed at. Composed steps are not rows of their own: the viz-node composes
//! and scores them again on its next start, as it does after a crash ([`crate::store::Recovery`]).
//! The damaged index is never deleted: it is renamed `index.sqlite.damaged-<seconds>`.

use crate::index::{holds_index, IndexDb, INDEX_DB};
use crate::rows::{refs_name, vdi_name, Entry, Placement, StoreError};
use crate::store::References;
use insitu_core::evaluate::Sizing;
use insitu_core::vdi::codec::{self, DecodeLimits};
use std::collections::BTreeMap;
use std::path::Path;

/// What a rebuild did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Rebuilt {
    /// Rows made, one per step and rank.
    pub rows: usize,
    /// Of them, rows with reference frames (scored on the viz-node's next start).
    pub with_references: usize,
    /// Steps of several ranks (composed on the viz-node's next start).
    pub multi_rank_steps: usize,
    /// Files of the old index, renamed beside it (`from → to`).
    pub set_aside: Vec<(String, String)>,
    /// Files left out, each with why.
    pub left_out: Vec<(String, String)>,
}

/// A rank's payload file name: its step and rank, and whether it is a VDI (else `.refs`).
fn rank_file(name: &str) -> Option<(u64, u32, bool)> {
    let rest = name.strip_prefix("step_")?;
    let (step, rest) = rest.split_once("_rank_")?;
    let (rank, is_vdi) = match rest.strip_suffix(".vdi") {
        Some(rank) => (rank, true),
        None => (rest.strip_suffix(".refs")?, false),
    };
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if !digits(step) || !digits(rank) {
        return None;
    }
    let (step, rank) = (step.parse().ok()?, rank.parse().ok()?);
    // Only the names the recording writes (zero-padded): no second file for one key.
    let own = if is_vdi {
        vdi_name(step, rank)
    } else {
        refs_name(step, rank)
    };
    (own == name).then_some((step, rank, is_vdi))
}

/// Rebuilds the index of the recording in `dir` from its files.
///
/// # Errors
/// [`StoreError::Corrupt`] naming the index when it is sound and holds rows (nothing to
/// rebuild: move it away first to rebuild anyway); [`StoreError::Io`] when the directory
/// cannot be read, a file renamed or the new index written.
pub fn rebuild(dir: &Path) -> Result<Rebuilt, StoreError> {
    let io = |path: &Path| {
        let path = path.to_owned();
        move |source| StoreError::Io { path, source }
    };
    let index = dir.join(INDEX_DB);
    if let Some(rows) = sound_rows(dir) {
        return Err(StoreError::Corrupt {
            path: index,
            problem: format!(
                "a sound index with {rows} rows: nothing to rebuild (move it away to rebuild from the files anyway)"
            ),
        });
    }
    let mut done = Rebuilt::default();
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    // A name no earlier rebuild used (two within a second get `-<secs>.1`, …).
    let stamp = (0..)
        .map(|k| match k {
            0 => secs.to_string(),
            k => format!("{secs}.{k}"),
        })
        .find(|s| !dir.join(format!("{INDEX_DB}.damaged-{s}")).exists())
        .unwrap_or_default();
    for suffix in ["", "-wal", "-shm"] {
        let from = format!("{INDEX_DB}{suffix}");
        let path = dir.join(&from);
        if path.exists() {
            let to = format!("{INDEX_DB}.damaged-{stamp}{suffix}");
            std::fs::rename(&path, dir.join(&to)).map_err(io(&path))?;
            done.set_aside.push((from, to));
        }
    }
    // Each entry with whether it is a regular file (not followed: a link is not one).
    let mut names: Vec<(String, bool)> = std::fs::read_dir(dir)
        .map_err(io(dir))?
        .filter_map(Result::ok)
        .map(|d| {
            let regular = d.file_type().is_ok_and(|t| t.is_file());
            (d.file_name().to_string_lossy().into_owned(), regular)
        })
        .collect();
    names.sort();
    let mut rows: BTreeMap<(u64, u32), Entry> = BTreeMap::new();
    let mut refs = Vec::new();
    for (name, regular) in names {
        if !regular {
            if rank_file(&name).is_some() {
                done.left_out.push((
                    name,
                    "not a regular file (a symbolic link, a directory or a device): recover reads the recording's own files only, never what a link points to".into(),
                ));
            }
            continue;
        }
        match rank_file(&name) {
            Some((step, rank, true)) => match row_of_vdi(&dir.join(&name), step, rank) {
                Ok(mut e) => {
                    e.vdi = Some(name);
                    rows.insert((step, rank), e);
                }
                Err(why) => done.left_out.push((name, why)),
            },
            Some((step, rank, false)) => refs.push((name, step, rank)),
            None => {}
        }
    }
    for (name, step, rank) in refs {
        match References::read_with_origin(&dir.join(&name)) {
            Ok((_, Some(origin))) if origin != (step, Some(rank)) => done.left_out.push((
                name,
                format!(
                    "it holds the frames of step {} rank {:?}, not those its name says",
                    origin.0, origin.1
                ),
            )),
            Ok(_) => {
                let e = rows
                    .entry((step, rank))
                    .or_insert_with(|| Entry::empty(step, rank));
                e.references = Some(name);
                e.with_references = true;
            }
            Err(e) => done.left_out.push((name, e.to_string())),
        }
    }
    let db = IndexDb::open(dir, true)?;
    let mut multi = std::collections::BTreeSet::new();
    for e in rows.values() {
        db.put_entry(e)?;
        done.rows += 1;
        done.with_references += usize::from(e.references.is_some() && e.vdi.is_some());
        if e.world_size > 1 {
            multi.insert(e.step);
        }
    }
    done.multi_rank_steps = multi.len();
    Ok(done)
}

/// The rows of the index in `dir` when it is sound and holds some.
fn sound_rows(dir: &Path) -> Option<usize> {
    if !holds_index(dir).ok()? {
        return None;
    }
    let db = IndexDb::open(dir, false).ok()?;
    db.check().ok()?;
    let rows = db.entries().ok()?.len();
    (rows > 0).then_some(rows)
}

/// A row from the VDI file at `path`, named for `step` and `rank`; why not, when its
/// provenance is missing or names another.
fn row_of_vdi(path: &Path, step: u64, rank: u32) -> Result<Entry, String> {
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    let (vdi, provenance) = codec::decode_with_provenance(&bytes, &DecodeLimits::default())
        .map_err(|e| e.to_string())?;
    let p = provenance.ok_or(
        "it carries no provenance (written before VDI files did): its world, P_M version and τ are unknown",
    )?;
    if (p.step, p.rank) != (step, rank) {
        return Err(format!(
            "it says it is the VDI of step {} rank {}, not the one its name says",
            p.step, p.rank
        ));
    }
    let meta = vdi.meta();
    Ok(Entry {
        step,
        rank,
        world_size: p.world_size,
        sim_time: p.sim_time,
        vdi: None,
        references: None,
        resolution: meta.params.resolution,
        gamma: meta.params.gamma,
        precision: meta.params.precision,
        codec: codec::codec_of(&bytes).ok(),
        sizing: Sizing {
            sigma_bytes: bytes.len() as u64,
            supersegments: vdi.supersegments().len() as u64,
            tau_secs: 0.0,
            tau_source: Default::default(),
            tau_compress_secs: 0.0,
        },
        tf_name: meta.tf_name.clone(),
        tf_hash: meta.tf_hash,
        quality: None,
        pm_version: p.pm_version,
        placement: p
            .placement
            .map(|(global_dims, brick)| Placement { global_dims, brick }),
        with_references: false,
        covers: if p.covers.len() > 1 {
            p.covers
        } else {
            Vec::new()
        },
        scene_version: p.scene_version,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::Recording;
    use insitu_core::vdi::codec::Codec;
    use insitu_core::vdi::provenance::Provenance;
    use insitu_core::volume::bricks::Brick;
    use insitu_core::{Camera, Image, RaycastParams, Raycaster, TransferFunction, VdiParams};

    /// Stores a VDI of `step` and `rank` (of a world of 2 split in x) as the service does,
    /// with reference frames when `refs`; returns its row.
    fn store(rec: &Recording, step: u64, rank: u32, refs: bool) -> Entry {
        let v =
            insitu_core::Volume::from_fn([8, 8, 8], |x, y, z| (x + y + z + step as usize) as f32)
                .unwrap();
        let tf = TransferFunction::default_for_range(0.0, 30.0);
        let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
        let camera = Camera::default_for_box(&v.world_box());
        let params = VdiParams {
            resolution: 16,
            gamma: 0.02,
            precision: Default::default(),
        };
        let vdi = insitu_core::vdi::generate::generate(&rc, &camera, params, 7, "ramp").unwrap();
        let brick = Brick {
            offset: [7 * rank as usize, 0, 0],
            dims: [8, 8, 8],
        };
        let p = Provenance {
            step,
            rank,
            world_size: 2,
            pm_version: 4,
            sim_time: step as f64 * 0.5,
            placement: Some(([15, 8, 8], brick)),
            covers: Vec::new(),
            scene_version: 2,
        };
        let bytes = codec::encode_with_provenance(&vdi, Codec::Zstd, Some(&p)).unwrap();
        let row = Entry {
            world_size: 2,
            sim_time: p.sim_time,
            resolution: 16,
            gamma: 0.02,
            codec: Some(Codec::Zstd),
            sizing: Sizing {
                sigma_bytes: bytes.len() as u64,
                supersegments: vdi.supersegments().len() as u64,
                tau_secs: 0.0,
                tau_source: Default::default(),
                tau_compress_secs: 0.0,
            },
            tf_name: "ramp".into(),
            tf_hash: 7,
            pm_version: 4,
            placement: Some(Placement {
                global_dims: [15, 8, 8],
                brick,
            }),
            with_references: refs,
            scene_version: 2,
            ..Entry::empty(step, rank)
        };
        let (mut e, _) = rec.store_vdi(row, &bytes).unwrap();
        if refs {
            let frames = References {
                camera,
                view_angles_deg: vec![0.0],
                frames: vec![Image::new(4, 4)],
                opacity: None,
            };
            e = rec.store_references(step, rank, &frames).unwrap().0;
        }
        e
    }

    fn rows(dir: &Path) -> Vec<Entry> {
        IndexDb::open(dir, false).unwrap().entries().unwrap()
    }

    #[test]
    fn an_emptied_or_cut_index_is_rebuilt_row_for_row_from_the_files() {
        for damage in ["emptied", "cut", "missing"] {
            let dir = tempfile::tempdir().unwrap();
            let rec = Recording::open(dir.path()).unwrap();
            let before: Vec<Entry> = [(1, 0, true), (1, 1, true), (2, 0, false)]
                .into_iter()
                .map(|(step, rank, refs)| store(&rec, step, rank, refs))
                .collect();
            // A later row than the ones above, to make the index span more than a page or two.
            for step in 10..40 {
                store(&rec, step, 0, false);
            }
            drop(rec);
            let index = dir.path().join(INDEX_DB);
            let _ = std::fs::remove_file(dir.path().join(format!("{INDEX_DB}-wal")));
            let _ = std::fs::remove_file(dir.path().join(format!("{INDEX_DB}-shm")));
            match damage {
                "emptied" => std::fs::write(&index, b"").unwrap(),
                "cut" => {
                    let len = std::fs::metadata(&index).unwrap().len();
                    let f = std::fs::OpenOptions::new()
                        .write(true)
                        .open(&index)
                        .unwrap();
                    f.set_len(len / 2).unwrap();
                }
                _ => std::fs::remove_file(&index).unwrap(),
            }
            let refused = Recording::open(dir.path()).err().map(|e| e.to_string());
            assert!(
                refused
                    .as_deref()
                    .is_some_and(|e| e.contains("insitu recover")),
                "{damage}: {refused:?}"
            );
            let done = rebuild(dir.path()).unwrap();
            assert_eq!(done.rows, 33, "{damage}: {done:?}");
            assert_eq!((done.with_references, done.multi_rank_steps), (2, 32));
            assert!(done.left_out.is_empty(), "{:?}", done.left_out);
            assert_eq!(
                done.set_aside.is_empty(),
                damage == "missing",
                "{damage}: {done:?}"
            );
            for (_, kept) in &done.set_aside {
                assert!(dir.path().join(kept).exists(), "{kept}");
            }
            let after = rows(dir.path());
            for want in &before {
                let got = after
                    .iter()
                    .find(|e| (e.step, e.rank) == (want.step, want.rank))
                    .unwrap();
                assert_eq!(got, want, "{damage}");
            }
            // The viz-node opens it again and sees what is left to score.
            let rec = Recording::open(dir.path()).unwrap();
            let todo = rec.recover().unwrap();
            assert_eq!(todo.files_without_rows, Vec::<String>::new());
            assert!(todo.uncomposed.contains(&1), "{todo:?}");
        }
    }

    #[test]
    fn files_that_cannot_say_where_they_belong_are_left_out_and_a_sound_index_is_kept() {
        let dir = tempfile::tempdir().unwrap();
        let rec = Recording::open(dir.path()).unwrap();
        store(&rec, 1, 0, true);
        store(&rec, 2, 0, false);
        assert!(rebuild(dir.path())
            .unwrap_err()
            .to_string()
            .contains("sound index with 2 rows"));
        drop(rec);
        std::fs::remove_file(dir.path().join(INDEX_DB)).unwrap();
        // Two files swapped by name, and one written without provenance.
        let (a, b) = (
            dir.path().join(vdi_name(1, 0)),
            dir.path().join(vdi_name(2, 0)),
        );
        let tmp = dir.path().join("swap");
        std::fs::rename(&a, &tmp).unwrap();
        std::fs::rename(&b, &a).unwrap();
        std::fs::rename(&tmp, &b).unwrap();
        let v = insitu_core::Volume::from_fn([4, 4, 4], |x, _, _| x as f32).unwrap();
        let tf = TransferFunction::default_for_range(0.0, 3.0);
        let rc = Raycaster::new(&v, &tf, RaycastParams::default()).unwrap();
        let cam = Camera::default_for_box(&v.world_box());
        let params = VdiParams {
            resolution: 8,
            gamma: 0.1,
            precision: Default::default(),
        };
        let old = insitu_core::vdi::generate::generate(&rc, &cam, params, 0, "x").unwrap();
        std::fs::write(
            dir.path().join(vdi_name(3, 0)),
            codec::encode(&old, Codec::None).unwrap(),
        )
        .unwrap();
        // A link named as a payload, to a good VDI outside the recording: never followed.
        #[cfg(unix)]
        {
            let outside = tempfile::tempdir().unwrap();
            let target = outside.path().join("elsewhere.vdi");
            std::fs::copy(&b, &target).unwrap();
            std::os::unix::fs::symlink(&target, dir.path().join(vdi_name(4, 0))).unwrap();
            let done = rebuild(dir.path()).unwrap();
            let why: BTreeMap<_, _> = done.left_out.iter().cloned().collect();
            assert!(
                why[&vdi_name(4, 0)].contains("not a regular file"),
                "{why:?}"
            );
            std::fs::remove_file(dir.path().join(vdi_name(4, 0))).unwrap();
            std::fs::remove_file(dir.path().join(INDEX_DB)).unwrap();
            for s in ["-wal", "-shm"] {
                let _ = std::fs::remove_file(dir.path().join(format!("{INDEX_DB}{s}")));
            }
        }
        let done = rebuild(dir.path()).unwrap();
        let why: BTreeMap<_, _> = done.left_out.iter().cloned().collect();
        assert!(why[&vdi_name(1, 0)].contains("step 2 rank 0"), "{why:?}");
        assert!(why[&vdi_name(2, 0)].contains("step 1 rank 0"), "{why:?}");
        assert!(why[&vdi_name(3, 0)].contains("no provenance"), "{why:?}");
        // The frames of step 1 stay, on a row without a VDI (a VDI may come later).
        let after = rows(dir.path());
        assert_eq!(after.len(), 1, "{after:?}");
        assert_eq!((after[0].step, after[0].vdi.as_deref()), (1, None));
    }

    #[test]
    fn only_the_recording_s_own_rank_file_names_parse() {
        assert_eq!(
            rank_file("step_00000012_rank_0003.vdi"),
            Some((12, 3, true))
        );
        assert_eq!(
            rank_file("step_00000012_rank_0003.refs"),
            Some((12, 3, false))
        );
        for other in [
            "step_00000012_composed.vdi",
            "step_12_rank_3.vdi",
            "step_00000012_rank_0003.vdi.tmp",
            "step_0000001x_rank_0003.vdi",
            "index.sqlite",
        ] {
            assert_eq!(rank_file(other), None, "{other}");
        }
    }
}
