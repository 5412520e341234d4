//! What a shipped VDI or set of reference frames must pass before it is stored: its header's
//! numbers, its placement in the grid, its ranks against the parts of its step already stored,
//! the provenance its file carries; then the store.

use super::*;

/// Checks a received VDI (`bytes`, with its header `h`) against what is stored, decodes it,
/// checks the header against the file, and stores it: its index entry, and whether it is new.
/// Decoded once: the VDI is kept for the scorer or the composer that reads it next.
pub(super) fn store_vdi(
    s: &Shared,
    h: &pb::VdiHeader,
    bytes: &[u8],
    placement: Option<Placement>,
) -> Result<(Entry, bool), Status> {
    let what = format!("VDI of step {} rank {}", h.step, h.rank);
    // The index and its JSON hold these as numbers: NaN or ±∞ has no place there.
    for (field, v, duration) in [
        ("tau_secs", h.tau_secs, true),
        ("tau_compress_secs", h.tau_compress_secs, true),
        ("sim_time", h.sim_time, false),
    ] {
        if !v.is_finite() || (duration && v < 0.0) {
            let must = if duration {
                "finite and non-negative"
            } else {
                "finite"
            };
            return Err(Status::invalid_argument(format!(
                "{what}: {field} {v} must be {must}"
            )));
        }
    }
    let ranks = part_ranks(h.step, h.rank, h.world_size, &h.covers)?;
    if let Some(held) = check_against_stored(&s.recording, h, &ranks, placement)? {
        info!(step = h.step, rank = h.rank, ranks = ?ranks, held_by = held.rank, "every rank of this part is stored already: acknowledged, not stored again");
        return Ok((held, false));
    }
    let (vdi, provenance) = codec::decode_with_provenance(bytes, &DecodeLimits::default())
        .map_err(|e| Status::invalid_argument(format!("{what}: {e}")))?;
    if let Some(p) = provenance {
        check_provenance(&what, h, (placement, &ranks), &p)?;
    }
    // Kept for the viewer's legend; a bad one costs the legend, not the VDI.
    if let Some(tf) = &h.tf {
        if let Err(e) = crate::tfs::keep(s.recording.dir(), h.tf_hash, tf) {
            warn!(step = h.step, rank = h.rank, error = %e, "the VDI's transfer function was not kept");
        }
    }
    let p = vdi.meta().params;
    if p.resolution != h.resolution || p.gamma.to_bits() != h.gamma.to_bits() {
        return Err(Status::invalid_argument(format!(
            "{what}: header says r = {}, γ = {} but the file holds r = {}, γ = {}",
            h.resolution, h.gamma, p.resolution, p.gamma
        )));
    }
    let tau_source = wire_enum::<pb::TauSource>(h.tau_source, "tau_source")
        .map(TimeSource::from)
        .map_err(|e| Status::invalid_argument(format!("{what}: {}", e.message())))?;
    let meta = Entry {
        step: h.step,
        rank: h.rank,
        world_size: h.world_size,
        sim_time: h.sim_time,
        vdi: None,
        references: None,
        resolution: h.resolution,
        gamma: h.gamma,
        precision: p.precision,
        codec: wire_enum::<pb::Codec>(h.codec, "codec").map(Option::<Codec>::from)?,
        sizing: Sizing {
            sigma_bytes: bytes.len() as u64,
            supersegments: vdi.supersegments().len() as u64,
            tau_secs: h.tau_secs,
            tau_source,
            tau_compress_secs: h.tau_compress_secs,
        },
        tf_name: vdi.meta().tf_name.clone(),
        tf_hash: vdi.meta().tf_hash,
        quality: None,
        pm_version: h.pm_version,
        placement,
        with_references: h.with_references,
        covers: if ranks.len() > 1 { ranks } else { Vec::new() },
        scene_version: h.scene_version,
    };
    let (entry, new) = s.recording.store_vdi(meta, bytes).map_err(store_status)?;
    let read_next = h.with_references || h.world_size > 1;
    if let (true, true, Some(name)) = (new, read_next, &entry.vdi) {
        s.kept.keep_vdi(name, vdi);
    }
    Ok((entry, new))
}

/// `INVALID_ARGUMENT` when the file says it comes from elsewhere in the run than its header
/// (`what` names the VDI): another step, rank, world, `P_M` version or brick.
pub(super) fn check_provenance(
    what: &str,
    h: &pb::VdiHeader,
    (placement, ranks): (Option<Placement>, &[u32]),
    p: &Provenance,
) -> Result<(), Status> {
    let file_placement = p
        .placement
        .map(|(global_dims, brick)| Placement { global_dims, brick });
    let disagree = [
        (
            "step",
            p.step != h.step,
            p.step.to_string(),
            h.step.to_string(),
        ),
        (
            "rank",
            p.rank != h.rank,
            p.rank.to_string(),
            h.rank.to_string(),
        ),
        (
            "world size",
            p.world_size != h.world_size.max(1),
            p.world_size.to_string(),
            h.world_size.to_string(),
        ),
        (
            "P_M version",
            p.pm_version != h.pm_version,
            p.pm_version.to_string(),
            h.pm_version.to_string(),
        ),
        (
            "scene version",
            p.scene_version != h.scene_version,
            p.scene_version.to_string(),
            h.scene_version.to_string(),
        ),
        (
            "brick",
            file_placement.is_some() && placement.is_some() && file_placement != placement,
            format!("{file_placement:?}"),
            format!("{placement:?}"),
        ),
        (
            "ranks held",
            p.ranks() != ranks,
            format!("{:?}", p.ranks()),
            format!("{ranks:?}"),
        ),
    ];
    match disagree.into_iter().find(|d| d.1) {
        Some((field, _, file, header)) => Err(Status::invalid_argument(format!(
            "{what}: the file's {field} is {file} but its header's is {header}: not this item's VDI"
        ))),
        None => Ok(()),
    }
}

/// The camera of a reference header whose frames' sides, view angles and byte count are
/// valid (`views × h × w × (3 | 4)` f32).
///
/// # Errors
/// `INVALID_ARGUMENT` naming the field at fault.
pub(super) fn reference_camera(h: &pb::ReferenceHeader) -> Result<insitu_core::Camera, Status> {
    let side_ok = |v: u32| (1..=MAX_IMAGE_SIDE).contains(&v);
    if !side_ok(h.width) || !side_ok(h.height) {
        return Err(Status::invalid_argument(format!(
            "reference frames of {}×{}: sides must be in 1..={MAX_IMAGE_SIDE}",
            h.width, h.height
        )));
    }
    let views = h.view_angles_deg.len();
    if views == 0 || views > MAX_VIEWS || h.view_angles_deg.iter().any(|a| !a.is_finite()) {
        return Err(Status::invalid_argument(format!(
            "{views} view angles: need 1..={MAX_VIEWS} finite angles"
        )));
    }
    let channels = if h.opacity { 4 } else { 3 };
    let expected = views as u64 * u64::from(h.width) * u64::from(h.height) * 4 * channels;
    if h.total_bytes != expected {
        return Err(Status::invalid_argument(format!(
            "total_bytes {} does not match {views} views of {}×{}×{channels} f32 ({expected})",
            h.total_bytes, h.width, h.height
        )));
    }
    let camera = h
        .camera
        .as_ref()
        .ok_or_else(|| Status::invalid_argument("camera is missing"))?;
    Camera::try_from(camera)
}

/// Parses received reference frames (`bytes`, with their header `h` and its `camera`) and
/// stores them: their index entry, and whether they are new (then kept, parsed, for the
/// scorer).
pub(super) fn store_references(
    s: &Shared,
    h: pb::ReferenceHeader,
    camera: insitu_core::Camera,
    bytes: &[u8],
) -> Result<(Entry, bool), Status> {
    let ranks = part_ranks(h.step, h.rank, u32::MAX, &h.covers)?;
    let stored: Vec<Entry> = s
        .recording
        .ranks_of(h.step)
        .into_iter()
        .filter(|e| e.vdi.is_some())
        .collect();
    if let Some(held) = held_elsewhere(&stored, h.step, (h.rank, &ranks), None)? {
        return Ok((held, false));
    }
    let size = (h.width, h.height);
    let refs =
        References::from_bytes(camera, h.view_angles_deg, size, h.opacity, bytes).map_err(|e| {
            Status::invalid_argument(format!(
                "references of step {} rank {}: {e}",
                h.step, h.rank
            ))
        })?;
    let (entry, new) = s
        .recording
        .store_references(h.step, h.rank, &refs)
        .map_err(store_status)?;
    if let (true, Some(name)) = (new, &entry.references) {
        s.kept.keep_references(name, refs);
    }
    Ok((entry, new))
}

/// The brick placement a VDI header states, when it states one.
///
/// # Errors
/// `INVALID_ARGUMENT` when only part of it is set or it does not fit the grid.
pub(super) fn placement(h: &pb::VdiHeader) -> Result<Option<Placement>, Status> {
    let d = |v: &Option<pb::Dims3>| v.as_ref().map(<[usize; 3]>::from);
    match (d(&h.global_dims), d(&h.brick_offset), d(&h.brick_dims)) {
        (None, None, None) => Ok(None),
        (Some(global_dims), Some(offset), Some(dims)) => {
            let p = Placement {
                global_dims,
                brick: Brick { offset, dims },
            };
            bricks::check(global_dims, &[(h.rank, p.brick)], false)
                .map_err(|e| Status::invalid_argument(format!("VDI of step {}: {e}", h.step)))?;
            Ok(Some(p))
        }
        _ => Err(Status::invalid_argument(format!(
            "VDI of step {} rank {}: global_dims, brick_offset and brick_dims must be set together",
            h.step, h.rank
        ))),
    }
}

/// The ranks a VDI or its frames hold, as their header states them (`covers`, or `rank`
/// alone), checked: ascending from `rank`, inside the world.
///
/// # Errors
/// `INVALID_ARGUMENT` naming the step, the rank and the list.
pub(super) fn part_ranks(
    step: u64,
    rank: u32,
    world_size: u32,
    covers: &[u32],
) -> Result<Vec<u32>, Status> {
    if covers.is_empty() {
        return Ok(vec![rank]);
    }
    if !insitu_core::vdi::provenance::covers_valid(rank, world_size.max(1), covers) {
        return Err(Status::invalid_argument(format!(
            "step {step} rank {rank}: covers {covers:?} must ascend from rank {rank} inside a world of {world_size}"
        )));
    }
    Ok(covers.to_vec())
}

/// The stored part of step `step` that already holds every rank of `ranks` when the part
/// `(rank, ranks)` is not itself stored: a generator-node restarted from its spool ships its
/// ranks again, alone or grouped otherwise than before (docs/scale.md). Acknowledged when
/// those parts carry `pm_version` too; `None` when the part is new or the same part again
/// (then the store compares bytes).
///
/// # Errors
/// `INVALID_ARGUMENT` naming the rank another part holds, when the part is not wholly held
/// or was made with another `P_M` version.
pub(super) fn held_elsewhere(
    stored: &[Entry],
    step: u64,
    (rank, ranks): (u32, &[u32]),
    pm_version: Option<u64>,
) -> Result<Option<Entry>, Status> {
    if stored.iter().any(|e| e.rank == rank && e.ranks() == ranks) {
        return Ok(None);
    }
    let holders: Vec<(u32, &Entry)> = ranks
        .iter()
        .filter_map(|&r| stored.iter().find(|e| e.holds(r)).map(|e| (r, e)))
        .collect();
    match holders.first() {
        None => Ok(None),
        Some(_)
            if holders.len() == ranks.len()
                && holders
                    .iter()
                    .all(|(_, e)| pm_version.is_none_or(|v| e.pm_version == v)) =>
        {
            Ok(Some(holders[0].1.clone()))
        }
        Some((r, e)) => Err(Status::invalid_argument(format!(
            "step {step}: rank {r} is already held by the stored part of rank {} (ranks {:?}, P_M version {}); this part of rank {rank} holds ranks {ranks:?}{}",
            e.rank,
            e.ranks(),
            e.pm_version,
            pm_version.map_or_else(String::new, |v| format!(" at P_M version {v}"))
        ))),
    }
}

/// Refuses a part whose world size, ranks or brick contradicts the parts of its step already
/// stored (a second world size, a rank another part holds, overlapping bricks, another grid),
/// naming the step and ranks. Returns the stored part that holds all of its ranks, when one
/// does ([`held_elsewhere`]): the part is then acknowledged, not stored.
///
/// # Errors
/// `INVALID_ARGUMENT` naming the contradiction.
pub(super) fn check_against_stored(
    rec: &insitu_recording::store::Recording,
    h: &pb::VdiHeader,
    ranks: &[u32],
    placement: Option<Placement>,
) -> Result<Option<Entry>, Status> {
    // Only parts whose VDI is stored have said a world size and a brick.
    let stored: Vec<Entry> = rec
        .ranks_of(h.step)
        .into_iter()
        .filter(|e| e.vdi.is_some())
        .collect();
    let others: Vec<&Entry> = stored.iter().filter(|e| e.rank != h.rank).collect();
    if let Some(o) = others.iter().find(|o| o.world_size != h.world_size) {
        return Err(Status::invalid_argument(format!(
            "step {}: rank {} says world size {}, but rank {} said {}",
            h.step, h.rank, h.world_size, o.rank, o.world_size
        )));
    }
    if let Some(held) = held_elsewhere(&stored, h.step, (h.rank, ranks), Some(h.pm_version))? {
        return Ok(Some(held));
    }
    let Some(p) = placement else { return Ok(None) };
    let this = Entry {
        placement: Some(p),
        ..Entry::empty(h.step, h.rank)
    };
    let mut all: Vec<&Entry> = others
        .into_iter()
        .filter(|o| o.placement.is_some())
        .collect();
    all.push(&this);
    crate::compose::check_bricks(h.step, &all, false)
        .map_err(|e| Status::invalid_argument(e.to_string()))?;
    Ok(None)
}
