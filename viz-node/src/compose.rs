//! One picture per step of a world of ranks (docs/conventions.md, "A world of ranks"):
//! once every rank's VDI (and, on sampled steps, its reference frames) is stored,
//! or `compose_timeout_secs` after the step's first rank arrived, the ranks' VDIs are merged
//! into one ([`insitu_core::compose::compose_vdis`]), their frames composited front to back
//! ([`insitu_core::compose::compose_frames`]), and the composed VDI scored against the
//! composed frames: that is the step's q.

use crate::score::score;
use insitu_core::compose::{compose_frames, compose_vdis, BrickFrame, ComposeError};
use insitu_core::vdi::codec::{self, Codec};
use insitu_core::vdi::provenance::Provenance;
use insitu_core::volume::bricks::{self, Brick, DecompositionError};
use insitu_core::{Backend, Vdi};
use insitu_recording::decoded::Kept;
use insitu_recording::store::{
    composed_refs_name, composed_vdi_name, write_atomic, Entry, Recording, References, StepEntry,
    StoreError,
};
use std::sync::Arc;

/// Why a step could not be composed; each names the step and the ranks.
#[derive(Debug, thiserror::Error)]
pub enum StepError {
    /// Bricks outside the grid, overlapping, or leaving gaps.
    #[error("step {step}: {source}")]
    Bricks {
        /// The step.
        step: u64,
        /// What is wrong.
        source: DecompositionError,
    },
    /// The ranks' VDIs were not made the same way.
    #[error("step {step}: rank {rank} differs from rank {first} in {what}")]
    Scene {
        /// The step.
        step: u64,
        /// The first rank.
        first: u32,
        /// The rank that differs.
        rank: u32,
        /// What differs.
        what: String,
    },
    /// Something about one rank's files or metadata.
    #[error("step {step} rank {rank}: {problem}")]
    Rank {
        /// The step.
        step: u64,
        /// The rank.
        rank: u32,
        /// What is wrong.
        problem: String,
    },
    /// The recording failed.
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// Whether `e` has everything its step's composition waits for.
pub fn ready(e: &Entry) -> bool {
    e.vdi.is_some() && (!e.with_references || e.references.is_some())
}

/// The ranks of `world_size` that no ready entry among `entries` holds (an entry holds its
/// rank, or every rank a host composed into it: [`Entry::ranks`]).
pub fn missing(entries: &[Entry], world_size: u32) -> Vec<u32> {
    let mut held = vec![false; world_size as usize];
    for e in entries.iter().filter(|e| ready(e)) {
        for r in e.ranks() {
            if let Some(h) = held.get_mut(r as usize) {
                *h = true;
            }
        }
    }
    (0..world_size).filter(|&r| !held[r as usize]).collect()
}

/// Checks the placement of `entries` (one step's ranks) against each other: the same grid,
/// bricks inside it with disjoint interiors and, when `complete`, covering it.
///
/// # Errors
/// [`StepError::Rank`] for a rank without a placement or on another grid,
/// [`StepError::Bricks`] otherwise.
pub fn check_bricks(step: u64, entries: &[&Entry], complete: bool) -> Result<(), StepError> {
    let mut global = None;
    let mut placed = Vec::with_capacity(entries.len());
    for e in entries {
        let p = e.placement.ok_or_else(|| StepError::Rank {
            step,
            rank: e.rank,
            problem: "its VDI does not say where its brick lies (a node older than composition)"
                .into(),
        })?;
        match global {
            None => global = Some(p.global_dims),
            Some(g) if g != p.global_dims => {
                return Err(StepError::Rank {
                    step,
                    rank: e.rank,
                    problem: format!(
                        "grid {:?} differs from the other ranks' {g:?}",
                        p.global_dims
                    ),
                })
            }
            Some(_) => {}
        }
        placed.push((e.rank, p.brick));
    }
    match global {
        Some(g) => {
            bricks::check(g, &placed, complete).map_err(|source| StepError::Bricks { step, source })
        }
        None => Ok(()),
    }
}

/// Rank `e`'s VDI: as kept on receipt, else read from the recording.
fn load_vdi(rec: &Recording, kept: &Kept, e: &Entry) -> Result<Arc<Vdi>, StepError> {
    let rank_err = |problem: String| StepError::Rank {
        step: e.step,
        rank: e.rank,
        problem,
    };
    let name = e.vdi.as_ref().ok_or_else(|| rank_err("no VDI".into()))?;
    kept.take_vdi(rec.dir(), name, e.into())
        .map_err(|err| rank_err(err.to_string()))
}

/// Composes the ready ranks of `step` (all of `world_size`, or those present when
/// `partial_ok`), stores the composed VDI and, when every rank sent frames with opacity, the
/// composed frames and q. Returns `None` when the step is not ready and `partial_ok` is false,
/// or when nothing of it is ready.
///
/// # Errors
/// [`StepError`] naming the step and ranks; the caller records it in the step's entry.
pub fn compose_step(
    rec: &Recording,
    kept: &Kept,
    backend: &Backend,
    termination: f32,
    step: u64,
    partial_ok: bool,
) -> Result<Option<StepEntry>, StepError> {
    let entries = rec.ranks_of(step);
    let Some(world_size) = entries.iter().map(|e| e.world_size).max() else {
        return Ok(None);
    };
    let missing = missing(&entries, world_size);
    let ready: Vec<&Entry> = entries.iter().filter(|e| ready(e)).collect();
    if ready.is_empty() || (!missing.is_empty() && !partial_ok) {
        return Ok(None);
    }
    check_bricks(step, &ready, missing.is_empty())?;
    let started = std::time::Instant::now();
    let vdis = ready
        .iter()
        .map(|e| load_vdi(rec, kept, e))
        .collect::<Result<Vec<_>, _>>()?;
    let composed = compose_ranks(step, &ready, &vdis)?;
    let vdi_name = store_composed(rec, step, &ready, &composed)?;
    let with_frames = ready.iter().all(|e| e.with_references);
    let mut compose_secs = started.elapsed().as_secs_f64();
    let (references, quality) = if with_frames {
        let t = std::time::Instant::now();
        let refs = compose_references(rec, kept, &ready, &vdis)?;
        compose_secs += t.elapsed().as_secs_f64();
        let name = composed_refs_name(step);
        write_atomic(rec.dir(), &name, &refs.to_file_bytes((step, None)))?;
        let q = score(backend, &composed, &refs, termination).map_err(|e| StepError::Rank {
            step,
            rank: ready[0].rank,
            problem: format!("scoring the composed VDI: {e}"),
        })?;
        (Some(name), Some(q))
    } else {
        (None, None)
    };
    let mut entry = StepEntry::of_ranks(step, world_size, &ready, missing);
    entry.sizing.supersegments = composed.supersegments().len() as u64;
    Ok(Some(StepEntry {
        vdi: Some(vdi_name),
        references,
        quality,
        compose_secs,
        ..entry
    }))
}

/// The ranks' VDIs (in `ready`'s order) composed into one ([`compose_vdis`]).
///
/// # Errors
/// [`StepError::Scene`] naming the first rank and the one whose scene differs;
/// [`StepError::Rank`] for any other failure.
fn compose_ranks(step: u64, ready: &[&Entry], vdis: &[Arc<Vdi>]) -> Result<Vdi, StepError> {
    if let Some(e) = ready
        .iter()
        .find(|e| e.scene_version != ready[0].scene_version)
    {
        return Err(StepError::Scene {
            step,
            first: ready[0].rank,
            rank: e.rank,
            what: format!(
                "steered scene version ({} against {})",
                e.scene_version, ready[0].scene_version
            ),
        });
    }
    compose_vdis(&vdis.iter().map(|v| &**v).collect::<Vec<_>>()).map_err(|e| match e {
        ComposeError::Mismatch { part, what } => StepError::Scene {
            step,
            first: ready[0].rank,
            rank: ready[part].rank,
            what: what.into(),
        },
        other => StepError::Rank {
            step,
            rank: ready[0].rank,
            problem: other.to_string(),
        },
    })
}

/// Writes the composed VDI of `step` in the first rank's codec (zstd when its node did not
/// name one) and returns its file name.
///
/// # Errors
/// [`StepError::Rank`] when it cannot be encoded, [`StepError::Store`] when it cannot be
/// written.
fn store_composed(
    rec: &Recording,
    step: u64,
    ready: &[&Entry],
    composed: &Vdi,
) -> Result<String, StepError> {
    let codec = ready[0].codec.unwrap_or(Codec::Zstd);
    // One VDI of the whole grid: a world of one.
    let provenance = Provenance {
        step,
        rank: 0,
        world_size: 1,
        pm_version: ready[0].pm_version,
        sim_time: ready[0].sim_time,
        covers: Vec::new(),
        scene_version: ready[0].scene_version,
        placement: ready[0]
            .placement
            .filter(|p| p.global_dims.iter().all(|&n| n >= 1))
            .map(|p| {
                let whole = Brick {
                    offset: [0; 3],
                    dims: p.global_dims,
                };
                (p.global_dims, whole)
            }),
    };
    let file = codec::encode_with_provenance(composed, codec, Some(&provenance)).map_err(|e| {
        StepError::Rank {
            step,
            rank: ready[0].rank,
            problem: format!("encoding the composed VDI: {e}"),
        }
    })?;
    let name = composed_vdi_name(step);
    write_atomic(rec.dir(), &name, &file)?;
    Ok(name)
}

/// The whole domain's reference frames from the ranks' (RGB + opacity), each view
/// composited front to back by ray entry into the ranks' boxes (taken from their VDIs).
fn compose_references(
    rec: &Recording,
    kept: &Kept,
    ready: &[&Entry],
    vdis: &[Arc<Vdi>],
) -> Result<References, StepError> {
    let all = rank_references(rec, kept, ready)?;
    let first = &all[0];
    let mut frames = Vec::with_capacity(first.frames.len());
    let mut planes = Vec::with_capacity(first.frames.len());
    for (view, &angle) in first.view_angles_deg.iter().enumerate() {
        let bricks: Vec<BrickFrame> = all
            .iter()
            .zip(vdis)
            .filter_map(|(r, v)| {
                Some(BrickFrame {
                    image: r.frames.get(view)?,
                    opacity: r.opacity.as_ref()?.get(view)?,
                    origin: [0, 0],
                    world_box: v.meta().volume_box,
                })
            })
            .collect();
        // The ranks' frames are all of the first's size (checked by `rank_references`).
        let size = bricks
            .first()
            .map_or((0, 0), |b| (b.image.width(), b.image.height()));
        let (image, opacity) = compose_frames(&first.camera.orbit_y(angle), size, &bricks)
            .map_err(|e| StepError::Rank {
                step: ready[0].step,
                rank: ready[0].rank,
                problem: format!("compositing reference frames: {e}"),
            })?;
        frames.push(image);
        planes.push(opacity);
    }
    Ok(References {
        camera: first.camera,
        view_angles_deg: first.view_angles_deg.clone(),
        frames,
        opacity: Some(planes),
    })
}

/// Each ready rank's reference frames, checked: every rank has frames with opacity, all
/// of the same views (camera, angles, frame size) as the first rank's.
///
/// # Errors
/// [`StepError::Rank`] for a rank without frames or opacity, [`StepError::Scene`] for views
/// that differ from the first rank's, [`StepError::Store`] when a file cannot be read.
fn rank_references(
    rec: &Recording,
    kept: &Kept,
    ready: &[&Entry],
) -> Result<Vec<Arc<References>>, StepError> {
    let mut all = Vec::with_capacity(ready.len());
    for e in ready {
        let rank_err = |problem: String| StepError::Rank {
            step: e.step,
            rank: e.rank,
            problem,
        };
        let name = e
            .references
            .as_ref()
            .ok_or_else(|| rank_err("no reference frames".into()))?;
        let refs = kept.take_references(rec.dir(), name)?;
        if refs.opacity.is_none() {
            return Err(rank_err(
                "reference frames without opacity cannot be composited (a node older than composition)"
                    .into(),
            ));
        }
        all.push(refs);
    }
    let first = &all[0];
    for (e, r) in ready.iter().zip(&all).skip(1) {
        let same = r.camera == first.camera
            && r.view_angles_deg == first.view_angles_deg
            && r.frames.first().map(|f| (f.width(), f.height()))
                == first.frames.first().map(|f| (f.width(), f.height()));
        if !same {
            return Err(StepError::Scene {
                step: e.step,
                first: ready[0].rank,
                rank: e.rank,
                what: "reference views (camera, angles or frame size)".into(),
            });
        }
    }
    Ok(all)
}
